//! The deployment files parse: the router's with zenoh's own parser, the service's with
//! scancorrd's (which also builds the zenoh configuration from it).

#[test]
fn deploy_configs_parse() {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../deploy");
    let router = zenoh::Config::from_file(dir.join("router.json5"))
        .expect("router.json5 is a valid zenoh configuration");
    let text = format!("{router}");
    assert!(
        text.contains("access_control") || text.contains("enabled"),
        "{text}"
    );
    zenoh::Config::from_file(dir.join("zenoh-client-tls.json5")).expect("zenoh-client-tls.json5");
    let op = zenoh::Config::from_file(dir.join("zenoh-operator-tls.json5"))
        .expect("zenoh-operator-tls.json5");
    assert!(op.get_json("connect/endpoints").unwrap().contains("tls/"));
    // A client file per role, each with the certificate of a subject the router's access
    // control names (issue 47: controller, app, operator, lab, auditor).
    let acl = router.get_json("access_control/subjects").unwrap();
    for (file, cn) in [
        ("zenoh-controller-tls.json5", "controller-m1"),
        ("zenoh-app-tls.json5", "app-shape-analysis"),
        ("zenoh-operator-tls.json5", "operator"),
        ("zenoh-lab-tls.json5", "lab-metrology"),
        ("zenoh-auditor-tls.json5", "auditor"),
    ] {
        let c = zenoh::Config::from_file(dir.join(file)).unwrap_or_else(|e| panic!("{file}: {e}"));
        assert!(
            c.get_json("connect/endpoints").unwrap().contains("tls/"),
            "{file}"
        );
        let cert = c
            .get_json("transport/link/tls/connect_certificate")
            .unwrap();
        assert!(cert.contains(&format!("/{cn}-cert.pem")), "{file}: {cert}");
        assert!(
            acl.contains(&format!("\"{cn}\"")),
            "{file}: `{cn}` is no subject of router.json5"
        );
        assert_eq!(c.get_json("mode").unwrap(), "\"client\"", "{file}");
    }
    let mut svc = scancorrd::Config::load(&dir.join("scancorrd.json5")).expect("scancorrd.json5");
    assert_eq!(svc.mode, "client");
    assert!(!svc.allow_any_machine && svc.serves("m1") && !svc.serves("m9"));
    svc.zenoh_config = Some(dir.join("zenoh-client-tls.json5"));
    svc.zenoh()
        .expect("the service builds its zenoh configuration");
    // Unknown fields are refused with the file named.
    let bad = std::env::temp_dir().join(format!("scancorrd-bad-{}.json5", std::process::id()));
    std::fs::write(&bad, "{ lisen: ['tcp/127.0.0.1:1'] }").unwrap();
    let e = scancorrd::Config::load(&bad).unwrap_err().to_string();
    assert!(e.contains("lisen"), "{e}");
    std::fs::remove_file(bad).ok();
}
