//! `scancorr view` live: scancorrd corrects a replayed ring; `scancorr view`, a client of the
//! bus, serves it as a Foxglove WebSocket; `tests/python/foxglove_view.py`, an independent
//! client of the protocol (the `websockets` package and Foxglove's published schemas), asks for
//! the `foxglove.websocket.v1` subprotocol, subscribes to the advertised channels and receives
//! every corrected point of the ring, in order, equal to the offline correction. With `--raw`
//! the machine's raw streams are channels too: the client decodes the scale channel with the
//! schema the server advertised, and each sample it gets is the bag's.

mod common;

use common::*;
use serde_json::Value;
use std::io::{BufRead, BufReader};

use std::process::{Command, Stdio};
use std::time::Duration;

/// Kills a child process when dropped (a failed assertion leaves nothing running).
struct Killed(std::process::Child);

impl Drop for Killed {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

#[test]
fn a_foxglove_websocket_client_receives_every_live_point_in_order() {
    let d = scratch("foxglove-view");
    ok(
        &d,
        &[
            "sim",
            "--program",
            "ring",
            "--seed",
            "5052",
            "--machine-seed",
            "5053",
            "--out",
            "r.mcap",
            "--calib-out",
            "v1.json",
        ],
    );
    ok(
        &d,
        &[
            "correct",
            "--bag",
            "r.mcap",
            "--calib",
            "v1.json",
            "--out",
            "off.mcap",
            "--no-foxglove",
        ],
    );
    let off = points(&d.join("off.mcap"));
    assert!(off.len() > 10_000, "{} points", off.len());

    let port = free_port();
    let bus = format!("tcp/127.0.0.1:{port}");
    let svc = Service::start(&d, port);
    calib_put(&d, "m1", "v1.json", &bus);
    let ws_port = free_port();
    let view_log = d.join("view.log");
    let view = Killed(
        Command::new(scancorr())
            .args([
                "view",
                "--port",
                &ws_port.to_string(),
                "--machine",
                "m1",
                "--raw",
            ])
            .args(["--nominal", "r.mcap", "--seconds", "60", "--connect", &bus])
            .current_dir(&d)
            .stdout(Stdio::null())
            .stderr(std::fs::File::create(&view_log).unwrap())
            .spawn()
            .unwrap(),
    );
    wait_listening(ws_port, || {
        format!(
            "scancorr view did not listen; its log:\n{}",
            std::fs::read_to_string(&view_log).unwrap_or_default()
        )
    });
    let mut client = Killed(
        Command::new(python())
            .arg(root().join("tests/python/foxglove_view.py"))
            .args([
                &ws_port.to_string(),
                "cmm/m1/foxglove/points",
                &off.len().to_string(),
                "30",
                "cmm/m1/raw/scale",
            ])
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap(),
    );
    // Subscribed before the first point is published.
    let mut err = BufReader::new(client.0.stderr.take().unwrap());
    let mut line = String::new();
    err.read_line(&mut line).unwrap();
    assert_eq!(line.trim(), "subscribed", "the client says: {line}");
    std::thread::sleep(Duration::from_millis(300));
    replay_max(&d, "r.mcap", &bus);
    svc.stop(); // flushes what the corrector holds
    let mut stdout = String::new();
    std::io::Read::read_to_string(client.0.stdout.as_mut().unwrap(), &mut stdout).unwrap();
    let status = client.0.wait().unwrap();
    let mut rest = String::new();
    std::io::Read::read_to_string(&mut err, &mut rest).unwrap();
    assert!(status.success(), "foxglove_view.py failed:\n{rest}");
    let r: Value = serde_json::from_str(&stdout).unwrap();
    assert_eq!(r["subprotocol"], "foxglove.websocket.v1", "{rest}");
    assert_eq!(r["server_info"]["op"], "serverInfo");
    let ch = &r["channels"]["cmm/m1/foxglove/points"];
    assert_eq!(ch["schemaName"], "foxglove.PointCloud", "{}", r["channels"]);
    assert_eq!(ch["encoding"], "protobuf");
    // The alarms, frame and nominal channels are advertised too; the latched frame and
    // nominal scene arrive on subscription.
    for t in ["alarms", "frame", "nominal", "deviation"] {
        assert!(
            r["channels"][format!("cmm/m1/foxglove/{t}")].is_object(),
            "{}",
            r["channels"]
        );
    }
    // Every topic the shipped layout names is one the view advertises.
    for p in foxglove_layout_paths() {
        let channels = r["channels"].as_object().unwrap();
        assert!(
            channels
                .keys()
                .any(|t| p == *t || p.starts_with(&format!("{t}."))),
            "the layout names `{p}`; the view advertises {:?}",
            channels.keys()
        );
    }
    assert_eq!(r["other_messages"]["cmm/m1/foxglove/frame"], 1, "{r}");
    assert_eq!(r["other_messages"]["cmm/m1/foxglove/nominal"], 1, "{r}");

    let got = r["points"].as_array().unwrap();
    assert_eq!(
        got.len(),
        off.len(),
        "points received vs offline; view log:\n{}",
        std::fs::read_to_string(&view_log).unwrap_or_default()
    );
    for (i, (g, o)) in got.iter().zip(&off).enumerate() {
        let s = o.surface.unwrap();
        let want = [
            (o.seq as u32) as f64,
            s.x / 1000.0,
            s.y / 1000.0,
            s.z / 1000.0,
        ];
        let g: Vec<f64> = g
            .as_array()
            .unwrap()
            .iter()
            .map(|v| v.as_f64().unwrap())
            .collect();
        assert_eq!(
            g, want,
            "point {i} (in order, equal to the offline correction)"
        );
    }

    // The raw scale stream on request: advertised with our schema, decoded by the client with
    // it, each sample the bag's (scancorrd's router may drop raw messages for a consumer that
    // falls behind, so some, in order, not necessarily all).
    let raw = &r["channels"]["cmm/m1/raw/scale"];
    assert_eq!(
        raw["schemaName"], "scancorr.v1.ScaleBatch",
        "{}",
        r["channels"]
    );
    assert_eq!(raw["schemaEncoding"], "protobuf");
    for t in ["command", "probe", "temperature"] {
        assert!(r["channels"][format!("cmm/m1/raw/{t}")].is_object());
    }
    let mut bag = std::collections::BTreeMap::new();
    let reader = scancorr_bag::BagReader::open(d.join("r.mcap")).unwrap();
    for m in reader.messages().unwrap() {
        let m = m.unwrap();
        if m.stream != scancorr_bag::Stream::Scale {
            continue;
        }
        let dec =
            scancorr_core::wire::decode(scancorr_core::wire::stream_id(m.stream).unwrap(), &m.data);
        for (_, s) in dec.unwrap().samples {
            if let scancorr_core::Sample::Scale(s) = s {
                bag.insert(s.seq, [s.t_ns as f64, s.pos.x, s.pos.y, s.pos.z]);
            }
        }
    }
    let got = r["raw"].as_array().unwrap();
    assert!(got.len() >= 100, "{} raw scale samples received", got.len());
    let mut last = None;
    for g in got {
        let g: Vec<f64> = g
            .as_array()
            .unwrap()
            .iter()
            .map(|v| v.as_f64().unwrap())
            .collect();
        let seq = g[0] as u64;
        assert!(last < Some(seq), "scale seq {seq} after {last:?}");
        last = Some(seq);
        assert_eq!(
            Some(&[g[1], g[2], g[3], g[4]]),
            bag.get(&seq),
            "scale sample {seq}"
        );
    }
    eprintln!("{} of {} raw scale samples received", got.len(), bag.len());
    drop(view);
}
