//! Issue 47: `scancorr-router --log-format json` writes one JSON object per line, its values
//! typed and without an escape byte when the log goes to a file; an access-control denial is
//! one of them, naming the key expression, the peer and the rule.

mod common;
use common::*;
use serde_json::Value;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_routers_json_log_is_typed_json_and_names_a_denial() {
    let d = scratch("ops-router-logs");
    let port = free_port();
    // Plain TCP on loopback; every local peer may put under `cmm/allowed/**` only.
    std::fs::write(
        d.join("router.json5"),
        format!(
            "{{ mode: 'router', listen: {{ endpoints: ['tcp/127.0.0.1:{port}'] }},
               scouting: {{ multicast: {{ enabled: false }} }},
               access_control: {{ enabled: true, default_permission: 'deny',
                 rules: [{{ id: 'allowed-puts', messages: ['put'], flows: ['ingress'],
                            permission: 'allow', key_exprs: ['cmm/allowed/**'] }}],
                 subjects: [{{ id: 'local', interfaces: ['lo'] }}],
                 policies: [{{ rules: ['allowed-puts'], subjects: ['local'] }}] }} }}"
        ),
    )
    .unwrap();
    let log = d.join("router.log");
    let mut router = Command::new(scancorrd().with_file_name("scancorr-router"))
        .args(["-c", "router.json5", "--log-format", "json"])
        .env_remove("NO_COLOR")
        .current_dir(&d)
        .stdout(Stdio::null())
        .stderr(std::fs::File::create(&log).unwrap())
        .spawn()
        .unwrap();
    // Routing once its session is open (it says so; it may route before).
    let t0 = Instant::now();
    while !std::fs::read_to_string(&log)
        .unwrap_or_default()
        .contains("\"routing\"")
    {
        assert!(
            t0.elapsed() < Duration::from_secs(20),
            "the router did not start:\n{}",
            std::fs::read_to_string(&log).unwrap_or_default()
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    let mut c = zenoh::Config::default();
    c.insert_json5("mode", "\"client\"").unwrap();
    c.insert_json5("connect/endpoints", &format!("[\"tcp/127.0.0.1:{port}\"]"))
        .unwrap();
    c.insert_json5("scouting/multicast/enabled", "false")
        .unwrap();
    let s = zenoh::open(c).await.unwrap();
    s.put("cmm/m1/raw/scale", b"x".to_vec()).await.unwrap();
    let t0 = Instant::now();
    while !std::fs::read_to_string(&log)
        .unwrap_or_default()
        .contains("ACL denied put (ingress) on cmm/m1/raw/scale")
    {
        assert!(
            t0.elapsed() < Duration::from_secs(10),
            "no denial logged:\n{}",
            std::fs::read_to_string(&log).unwrap_or_default()
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    s.close().await.unwrap();
    let _ = Command::new("kill")
        .args(["-TERM", &router.id().to_string()])
        .status();
    assert!(router.wait().unwrap().success());

    let bytes = std::fs::read(&log).unwrap();
    assert!(!bytes.contains(&0x1b), "an escape byte in a log file");
    let text = String::from_utf8(bytes).unwrap();
    let lines: Vec<Value> = text
        .lines()
        .map(|l| serde_json::from_str(l).unwrap_or_else(|e| panic!("not JSON ({e}): {l}")))
        .collect();
    let denied = lines
        .iter()
        .find(|l| {
            l["message"]
                .as_str()
                .is_some_and(|m| m.starts_with("ACL denied put (ingress) on cmm/m1/raw/scale"))
        })
        .unwrap_or_else(|| panic!("{text}"));
    assert_eq!(denied["level"], "WARN", "{denied}");
    assert_eq!(denied["key_expr"], "cmm/m1/raw/scale", "{denied}");
    assert_eq!(denied["kind"], "put", "{denied}");
    assert!(
        denied["rule"]
            .as_str()
            .is_some_and(|r| r.contains("subject local")),
        "{denied}"
    );
    assert!(denied["repeats_since_last"].is_u64(), "a number: {denied}");
    assert!(
        lines
            .iter()
            .any(|l| l["message"] == "routing" && l["zid"].is_string()),
        "{text}"
    );
}
