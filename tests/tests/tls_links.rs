//! A TLS link that carries traffic both ways at once keeps every message and stays up.
//!
//! The shipped router (`scancorr-router`, TLS with client certificates as in
//! `deploy/router.json5`) and two client sessions of this process, each publishing as fast as
//! the link takes it (`Block`) while it receives the other's messages: every link of the
//! router reads and writes at the same moment, as the service's link does while a controller
//! streams samples in and the service streams points out.
//!
//! zenoh-link-tls 1.10.2 reads and writes one rustls connection from two tasks without a lock
//! (eclipse-zenoh/zenoh#2557). rustls empties the connection's state while it processes the
//! records it read, so a write in that window failed with "HandshakeNotComplete" and the link
//! closed; a torn read of that state made the router abort in CI ("memory allocation of
//! 140225783298400 bytes failed", in `rustls::Error::clone`). The workspace builds the crate
//! from `third_party/zenoh-link-tls`, which holds the connection under a lock for each poll.
//! This test fails on the unpatched crate: messages lost, a liveliness token dropped (its
//! session's link closed and came back), or the router gone.

mod common;
use common::*;
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
use zenoh::qos::CongestionControl;
use zenoh::sample::SampleKind;
use zenoh::Wait;

/// How long each session publishes.
const SEND_FOR: Duration = Duration::from_secs(6);
/// Bytes per message: several TLS records' worth of work per read, so that the reading and
/// the writing task of a link overlap often.
const PAYLOAD: usize = 4096;

struct Router(Child);

impl Drop for Router {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// A client session with `who`'s certificate (made by `scripts/make-certs.sh`).
fn client(certs: &Path, who: &str, port: u16) -> zenoh::Session {
    let mut c = zenoh::Config::default();
    let s = |p: &str| format!("\"{}\"", certs.join(p).display());
    for (k, v) in [
        ("mode", "\"client\"".to_string()),
        ("connect/endpoints", format!("[\"tls/127.0.0.1:{port}\"]")),
        ("scouting/multicast/enabled", "false".into()),
        ("transport/link/tls/root_ca_certificate", s("ca.pem")),
        (
            "transport/link/tls/connect_private_key",
            s(&format!("{who}-key.pem")),
        ),
        (
            "transport/link/tls/connect_certificate",
            s(&format!("{who}-cert.pem")),
        ),
        ("transport/link/tls/enable_mtls", "true".into()),
    ] {
        c.insert_json5(k, &v).unwrap();
    }
    zenoh::open(c).wait().expect("a client connects over TLS")
}

/// What one side received: the next number it expects, and the first gap in the numbering.
#[derive(Default)]
struct Seen {
    next: u64,
    gap: Option<(u64, u64)>,
}

#[test]
fn tls_links_carry_traffic_both_ways_without_failing() {
    let d = scratch("tls-links");
    let certs = make_certs(&d);
    let port = free_port();
    let c = |p: &str| certs.join(p).display().to_string();
    std::fs::write(
        d.join("router.json5"),
        format!(
            r#"{{ mode: "router", listen: {{ endpoints: ["tls/127.0.0.1:{port}"] }},
                scouting: {{ multicast: {{ enabled: false }} }},
                transport: {{ link: {{ tls: {{ root_ca_certificate: "{}",
                  listen_private_key: "{}", listen_certificate: "{}", enable_mtls: true }} }} }} }}"#,
            c("ca.pem"),
            c("router-key.pem"),
            c("router-cert.pem")
        ),
    )
    .unwrap();
    let log = d.join("router.log");
    let mut router = Router(
        Command::new(scancorrd().with_file_name("scancorr-router"))
            .args(["-c", "router.json5"])
            .current_dir(&d)
            .stdout(Stdio::null())
            .stderr(std::fs::File::create(&log).unwrap())
            .spawn()
            .expect("scancorr-router starts"),
    );
    wait_listening(port, || "the router did not start".into());
    let router_log = || std::fs::read_to_string(&log).unwrap_or_default();

    let a = client(&certs, "scancorrd", port);
    let b = client(&certs, "controller-m1", port);
    // Each session's liveliness token, watched by the other: a link that closes takes the
    // token with it (a `Delete`), even when the session connects again.
    let dropped = Arc::new(AtomicU64::new(0));
    let _ta = a.liveliness().declare_token("tls-test/a").wait().unwrap();
    let _tb = b.liveliness().declare_token("tls-test/b").wait().unwrap();
    let watch = |s: &zenoh::Session, key: &str| {
        let dropped = dropped.clone();
        s.liveliness()
            .declare_subscriber(key)
            .callback(move |t| {
                if t.kind() == SampleKind::Delete {
                    dropped.fetch_add(1, Ordering::Relaxed);
                }
            })
            .wait()
            .unwrap()
    };
    let _wa = watch(&a, "tls-test/b");
    let _wb = watch(&b, "tls-test/a");
    // Each side numbers its messages; the other checks that they arrive in order, none missing.
    let listen = |s: &zenoh::Session, key: &str| {
        let seen = Arc::new(Mutex::new(Seen::default()));
        let g = seen.clone();
        let sub = s
            .declare_subscriber(key)
            .callback(move |m| {
                let bytes = m.payload().to_bytes();
                let n = u64::from_le_bytes(bytes[..8].try_into().unwrap());
                let mut g = g.lock().unwrap();
                if n != g.next && g.gap.is_none() {
                    g.gap = Some((g.next, n));
                }
                g.next = n + 1;
            })
            .wait()
            .unwrap();
        (seen, sub)
    };
    let (at_b, _sb) = listen(&b, "tls-test/from-a");
    let (at_a, _sa) = listen(&a, "tls-test/from-b");
    let send = |s: zenoh::Session, key: &'static str| {
        std::thread::spawn(move || {
            let p = s
                .declare_publisher(key)
                .congestion_control(CongestionControl::Block)
                .wait()
                .unwrap();
            let t0 = Instant::now();
            while !p.matching_status().wait().unwrap().matching() {
                assert!(
                    t0.elapsed() < Duration::from_secs(10),
                    "{key}: nobody listens"
                );
                std::thread::sleep(Duration::from_millis(20));
            }
            let mut buf = vec![0x5a_u8; PAYLOAD];
            let (t0, mut n) = (Instant::now(), 0u64);
            while t0.elapsed() < SEND_FOR {
                buf[..8].copy_from_slice(&n.to_le_bytes());
                if let Err(e) = p.put(buf.clone()).wait() {
                    return Err(format!("{key}: put {n}: {e}"));
                }
                n += 1;
            }
            Ok(n)
        })
    };
    let (sa, sb) = (
        send(a.clone(), "tls-test/from-a"),
        send(b.clone(), "tls-test/from-b"),
    );
    let sent_a = sa.join().unwrap().unwrap();
    let sent_b = sb.join().unwrap().unwrap();
    // What is still on its way arrives within a few seconds.
    let t0 = Instant::now();
    while (at_b.lock().unwrap().next < sent_a || at_a.lock().unwrap().next < sent_b)
        && t0.elapsed() < Duration::from_secs(10)
    {
        std::thread::sleep(Duration::from_millis(50));
    }
    let alive = router.0.try_wait().unwrap().is_none();
    let (ab, ba) = (at_b.lock().unwrap(), at_a.lock().unwrap());
    let report = format!(
        "a → b: {} of {sent_a} (first gap {:?}); b → a: {} of {sent_b} (first gap {:?}); \
         tokens dropped: {}; router alive: {alive}\nrouter:\n{}",
        ab.next,
        ab.gap,
        ba.next,
        ba.gap,
        dropped.load(Ordering::Relaxed),
        router_log()
    );
    eprintln!("{}", report.lines().next().unwrap());
    assert!(alive, "{report}");
    assert!(
        sent_a > 1000 && sent_b > 1000,
        "too little traffic: {report}"
    );
    assert_eq!((ab.next, ab.gap), (sent_a, None), "{report}");
    assert_eq!((ba.next, ba.gap), (sent_b, None), "{report}");
    assert_eq!(dropped.load(Ordering::Relaxed), 0, "{report}");
}
