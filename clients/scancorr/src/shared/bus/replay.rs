//! `replay`: a bag's raw streams onto the bus, paced by sample time, and the ledger that
//! confirms each machine's messages reached the scancorrd serving it (or names the router's
//! refusal).

use super::*;

/// How long a publisher waits for a subscriber before giving up.
const MATCH_WAIT: Duration = Duration::from_secs(5);

/// What a replay sent, and what became of it.
#[derive(Debug, Clone, Copy, Default)]
pub struct Replayed {
    /// Messages published.
    pub sent: u64,
    /// Of those, how many did not reach the scancorrd serving their machine (lost on the way:
    /// a link closed, a router down); None when no scancorrd answered to confirm.
    pub not_delivered: Option<u64>,
    /// Of those that arrived, how many the service shed (it could not correct them in real
    /// time; counted on the machine's status as `input.shed`).
    pub shed: u64,
}

impl Replayed {
    /// What became of them, in words (empty when everything arrived and was corrected).
    pub fn said(&self) -> String {
        let mut v = vec![];
        match self.not_delivered {
            Some(0) => {}
            Some(n) => v.push(format!("{n} did not reach scancorrd")),
            None => v.push("their arrival is not confirmed (no scancorrd answered)".into()),
        }
        if self.shed > 0 {
            v.push(format!("{} were shed by scancorrd", self.shed));
        }
        if v.is_empty() {
            String::new()
        } else {
            format!(" ({})", v.join("; "))
        }
    }
}

/// `replay`: bag → bus, paced by sample time (`rate` × real time; None = as fast as possible).
pub fn replay(bus: &Bus, bag: &Path, rate: Option<f64>, looping: bool) -> Result<Replayed> {
    bus.check()?;
    // Read the bag before connecting: a bad bag is reported as such.
    BagReader::open(bag).with_context(|| format!("reading bag {}", bag.display()))?;
    connect(bus)?.replay(bus, bag, rate, looping)
}

impl Conn {
    /// Publishes a bag's raw streams; fails when nobody subscribes to them. Closes once every
    /// message has arrived at the scancorrd serving its machine (a query that travels behind
    /// them comes back with their count), or says how many did not.
    pub fn replay(
        &self,
        bus: &Bus,
        bag: &Path,
        rate: Option<f64>,
        looping: bool,
    ) -> Result<Replayed> {
        let reader =
            BagReader::open(bag).with_context(|| format!("reading bag {}", bag.display()))?;
        let s = &self.session;
        self.rt.block_on(async {
            let mut pubs = std::collections::BTreeMap::new();
            for ch in reader.channels() {
                if Stream::RAW.contains(&ch.stream) {
                    crate::shared::output::check_machine("the bag's machine", &ch.machine)?;
                    let key = ch.stream.key(&bus.prefix, &ch.machine);
                    let p = s
                        .declare_publisher(key.clone())
                        .congestion_control(CongestionControl::Block)
                        .await
                        .map_err(z)?;
                    pubs.insert(ch.topic.clone(), (key, p, ch.machine.clone()));
                }
            }
            if pubs.is_empty() {
                bail!("{}: no raw streams to publish", bag.display());
            }
            // Wait until someone listens (the route is set up).
            let t0 = Instant::now();
            let matched = loop {
                let mut matched = vec![];
                for (key, p, _) in pubs.values() {
                    if p.matching_status().await.map(|m| m.matching()).unwrap_or(false) {
                        matched.push(key.clone());
                    }
                }
                if matched.len() == pubs.len() || t0.elapsed() > MATCH_WAIT {
                    break matched;
                }
                tokio::time::sleep(Duration::from_millis(50)).await;
            };
            if matched.is_empty() {
                bail!(
                    "nobody subscribes to {} on {} (waited {} s): is scancorrd running there with prefix `{}`?",
                    pubs.values().map(|(k, _, _)| format!("`{k}`")).collect::<Vec<_>>().join(", "),
                    bus.endpoints(),
                    MATCH_WAIT.as_secs(),
                    bus.prefix
                );
            }
            for (key, _, _) in pubs.values() {
                if !matched.contains(key) {
                    eprintln!("warning: nobody subscribes to `{key}`; its messages go nowhere");
                }
            }
            // What the service serving each machine has received of it so far: the replay's
            // messages are counted against it at the end (none: no scancorrd answers for it,
            // and delivery cannot be confirmed).
            let machines: std::collections::BTreeSet<String> =
                pubs.values().map(|(_, _, m)| m.clone()).collect();
            let mut ledgers = std::collections::BTreeMap::new();
            for m in &machines {
                let before = input_of(s, &bus.prefix, m, ASK_FIRST).await;
                let pacing = before.is_some();
                ledgers.insert(m.clone(), Ledger { before, sent: 0, pacing });
            }
            let mut sent = 0u64;
            let mut progress = crate::shared::output::Progress::new();
            let total = reader.message_count();
            loop {
                let start = Instant::now();
                let mut first: Option<u64> = None;
                for m in reader.messages()? {
                    let m = m?;
                    let Some((_, p, machine)) = pubs.get(&*m.topic) else {
                        continue;
                    };
                    if let Some(r) = rate {
                        let f = *first.get_or_insert(m.publish_time);
                        let due = Duration::from_secs_f64(
                            (m.publish_time.saturating_sub(f)) as f64 * 1e-9 / r,
                        );
                        if let Some(wait) = due.checked_sub(start.elapsed()) {
                            tokio::time::sleep(wait).await;
                        }
                    }
                    // Bags recorded before scancorr.v1.1 hold untagged batches; their
                    // channel names the stream, so the tag is added on the way out.
                    let data = match scancorr_core::wire::stream_id(m.stream) {
                        Some(sid) => scancorr_core::wire::tagged(sid, &m.data)
                            .map(|b| b.into_owned())
                            .with_context(|| format!("{}: message on `{}`", bag.display(), m.topic))?,
                        None => m.data.to_vec(),
                    };
                    p.put(data).await.map_err(z)?;
                    sent += 1;
                    let l = ledgers.get_mut(machine).expect("a ledger per machine");
                    l.sent += 1;
                    // As fast as possible: paced by the service, so that what it has not
                    // corrected yet of this machine stays small (it never waits for a
                    // publisher; what it cannot hold, it sheds).
                    if rate.is_none() && l.pacing && l.sent % PACE_EVERY == 0 {
                        l.pacing = pace(s, &bus.prefix, machine).await;
                    }
                    progress.tick(|| format!("replaying {}: {sent} of {total} message(s){}", bag.display(), if looping { " (looping)" } else { "" }));
                }
                if !looping {
                    break;
                }
            }
            progress.finish();
            // Every message has left, and arrived, once the service has counted them: a
            // query travels behind them, in the same queue, over the same links.
            let mut lost = vec![];
            let mut unconfirmed = vec![];
            let mut uncorrected: Vec<String> = vec![];
            let mut replayed = Replayed { sent, not_delivered: Some(0), shed: 0 };
            for (m, l) in &ledgers {
                let Some(before) = &l.before else {
                    unconfirmed.push(m.clone());
                    continue;
                };
                let after = settle(s, &bus.prefix, m, before.arrived + l.sent).await;
                let Some(after) = after else {
                    unconfirmed.push(m.clone());
                    continue;
                };
                let arrived = after.arrived.saturating_sub(before.arrived).min(l.sent);
                if after.calibrated == Some(false) && arrived > 0 {
                    uncorrected.push(m.clone());
                }
                let shed = after.shed.saturating_sub(before.shed).min(arrived);
                replayed.shed += shed;
                if let Some(n) = &mut replayed.not_delivered {
                    *n += l.sent - arrived;
                }
                if shed > 0 {
                    eprintln!(
                        "warning: scancorrd had shed {shed} of the {} message(s) of machine `{m}` when the replay ended: it could not correct them in real time (`input` on its status: `scancorr status --machine {m}`)",
                        l.sent
                    );
                }
                if arrived < l.sent {
                    lost.push(format!("{} of {} for machine `{m}`", l.sent - arrived, l.sent));
                }
            }
            if !unconfirmed.is_empty() || !lost.is_empty() {
                // Refused by a router's access control? `scancorr-router` says what it denied
                // this session; else a machine seen served whose status did not answer.
                let keys: Vec<&String> = pubs.values().map(|(k, _, _)| k).collect();
                if let Some(e) = refusal(s, bus, &keys, &unconfirmed, sent).await {
                    return Err(e);
                }
            }
            if !unconfirmed.is_empty() {
                replayed.not_delivered = None;
                // Without a service to count them: time for the last messages to leave.
                tokio::time::sleep(Duration::from_millis(300)).await;
                eprintln!(
                    "warning: no scancorrd answered for machine(s) {}: whether their messages arrived is not confirmed",
                    unconfirmed.iter().map(|m| format!("`{m}`")).collect::<Vec<_>>().join(", ")
                );
            }
            if !lost.is_empty() {
                // Said, not failed: a replay that outlived a router restart goes on, and the
                // service counts the samples missing too.
                eprintln!(
                    "warning: messages published did not reach scancorrd ({}): they were lost on the way (a link closed, a router was down)",
                    lost.join(", ")
                );
            }
            // A subscriber that went away (the service stopped) did not get everything.
            let mut still = false;
            for (_, p, _) in pubs.values() {
                still |= p.matching_status().await.map(|m| m.matching()).unwrap_or(false);
            }
            if !still {
                bail!(
                    "the subscribers on {} went away during the replay: some of the {sent} message(s) were not delivered",
                    bus.endpoints()
                );
            }
            if let Some(first) = uncorrected.first() {
                bail!(
                    "scancorrd has no calibration in use for machine(s) {}: it counted what they streamed as uncorrected and published no point (`scancorr status --machine {first}`); put one first: `scancorr calib put --machine {first} --file CALIBRATION.json`",
                    uncorrected.iter().map(|m| format!("`{m}`")).collect::<Vec<_>>().join(", ")
                );
            }
            Ok(replayed)
        })
    }
}

/// The key of `scancorr-router`'s queryable that answers what its access control denied a
/// session (`?zid=<the session's zenoh id>`): a JSON list of `{message, flow, key, peer, rule,
/// count}`.
pub const ROUTER_DENIED_KEY: &str = "@scancorr/router/denied";

/// What the router this session goes through denied it; None when no `scancorr-router`
/// answers (no router, another router, or an access control that does not allow asking).
async fn router_denials(s: &zenoh::Session) -> Option<Vec<serde_json::Value>> {
    let selector = format!("{ROUTER_DENIED_KEY}?zid={}", s.zid());
    let docs = json_answers(s, selector, Duration::from_millis(1500)).await?;
    let lists: Vec<&Vec<serde_json::Value>> = docs.iter().filter_map(|v| v.as_array()).collect();
    (!lists.is_empty()).then(|| lists.into_iter().flatten().cloned().collect())
}

/// Publications refused on their way, as the router that refused them tells (`scancorr-router`:
/// the puts on `keys` it denied this session, with the rule): the error to fail with. Else, a
/// machine of `unconfirmed` whose scancorrd is seen (its liveliness token) while its status
/// did not answer this session is said in a warning (a router's access control drops a denied
/// query, and may have denied the puts as well; or the service did not answer in time).
async fn refusal(
    s: &zenoh::Session,
    bus: &Bus,
    keys: &[&String],
    unconfirmed: &[String],
    sent: u64,
) -> Option<anyhow::Error> {
    let who = match bus.config().ok().as_ref().and_then(certificate_cn) {
        Some(cn) => format!("this session: certificate CN `{cn}`, zenoh id {}", s.zid()),
        None => format!("this session: zenoh id {}, no certificate", s.zid()),
    };
    // The router notes a denial within milliseconds of it: asked again once if it answered
    // with none.
    let mut denied = vec![];
    for _ in 0..2 {
        let Some(list) = router_denials(s).await else {
            break;
        };
        denied = list
            .into_iter()
            .filter(|d| {
                d["message"] == "put"
                    && d["key"]
                        .as_str()
                        .is_some_and(|k| keys.iter().any(|x| x.as_str() == k))
            })
            .collect();
        if !denied.is_empty() {
            break;
        }
        tokio::time::sleep(Duration::from_millis(300)).await;
    }
    if !denied.is_empty() {
        let each: Vec<String> = denied
            .iter()
            .map(|d| {
                format!(
                    "{} put(s) on `{}` ({})",
                    d["count"],
                    d["key"].as_str().unwrap_or("?"),
                    d["rule"].as_str().unwrap_or("?")
                )
            })
            .collect();
        return Some(anyhow::anyhow!(
            "refused: the router's access control denied the publications of {who}: {}; they were refused on their way and never reached scancorrd (of the {sent} message(s) published); check its rules for this session's certificate role (deploy/router.json5)",
            each.join("; ")
        ));
    }
    for m in unconfirmed {
        let token = format!("{}/{m}/scancorrd", bus.prefix);
        if token_seen(s, &token, Duration::from_secs(1)).await {
            eprintln!(
                "warning: no answer on `{}/{m}/status` although scancorrd serves machine `{m}` (its liveliness token `{token}` is seen): the query may have been refused on its way — a router's access control drops a denied query without telling the asker, and may have refused the messages published for it too ({who}; check its rules for this session's certificate role, deploy/router.json5) — or the service did not answer in time",
                bus.prefix
            );
        }
    }
    None
}

/// How long the first question to the service may take to answer (a machine's status).
const ASK_FIRST: Duration = Duration::from_secs(3);

/// With `--speed max` / `--live-rate max`, the service is asked every this many messages of a
/// machine how much of it waits to be corrected.
const PACE_EVERY: u64 = 32;

/// Publishing waits while more than this of a machine waits in the service, bytes…
const PACE_HIGH: u64 = 1 << 20;

/// … until it is below this.
const PACE_LOW: u64 = 256 << 10;

/// What a service has received of one machine (its status' `input`).
#[derive(Debug, Clone, Copy, PartialEq)]
struct Received {
    arrived: u64,
    shed: u64,
    queued_bytes: u64,
    /// Whether a calibration is in use (None: a service too old to say).
    calibrated: Option<bool>,
}

/// A machine's messages in a replay: what its service had received before, and what was sent.
struct Ledger {
    before: Option<Received>,
    sent: u64,
    /// Paced by the service (it answers).
    pacing: bool,
}

/// What the scancorrd serving `machine` has received of it (`status?input`, answered at once
/// from the counters of its input); zero for a machine it does not serve yet; None when no
/// scancorrd answers within `wait`.
async fn input_of(
    s: &zenoh::Session,
    prefix: &str,
    machine: &str,
    wait: Duration,
) -> Option<Received> {
    let mut best: Option<Received> = None;
    for v in json_answers(s, format!("{prefix}/{machine}/status?input"), wait).await? {
        let got = if v["served"] == true {
            let i = &v["input"];
            // A service older than the `input` counters cannot confirm anything.
            let Some(arrived) = i["arrived"].as_u64() else {
                continue;
            };
            Received {
                arrived,
                shed: i["shed"].as_u64().unwrap_or(0),
                queued_bytes: i["queued_bytes"].as_u64().unwrap_or(0),
                calibrated: v["calibrated"].as_bool(),
            }
        } else {
            Received {
                arrived: 0,
                shed: 0,
                queued_bytes: 0,
                calibrated: None,
            }
        };
        if best.is_none_or(|b| got.arrived > b.arrived) {
            best = Some(got);
        }
    }
    best
}

/// Waits while the service holds more than [`PACE_HIGH`] of `machine` not yet corrected;
/// false when it no longer answers (the replay goes on unpaced).
async fn pace(s: &zenoh::Session, prefix: &str, machine: &str) -> bool {
    let t0 = Instant::now();
    let mut high = PACE_HIGH;
    while t0.elapsed() < Duration::from_secs(30) {
        match input_of(s, prefix, machine, Duration::from_secs(2)).await {
            Some(r) if r.queued_bytes > high => {
                high = PACE_LOW;
                tokio::time::sleep(Duration::from_millis(5)).await;
            }
            Some(_) => return true,
            None => return false,
        }
    }
    true
}

/// What the service has received of `machine` once it has `expect` messages, or once the count
/// stops growing (a query behind the replay's messages came back and the next ones say the
/// same); None when it stops answering.
async fn settle(s: &zenoh::Session, prefix: &str, machine: &str, expect: u64) -> Option<Received> {
    let t0 = Instant::now();
    let mut last: Option<Received> = None;
    let mut same = 0;
    loop {
        let r = input_of(s, prefix, machine, Duration::from_secs(5)).await?;
        if r.arrived >= expect || t0.elapsed() > Duration::from_secs(20) {
            return Some(r);
        }
        if last.is_some_and(|l| l.arrived == r.arrived) {
            same += 1;
            if same >= 5 {
                return Some(r);
            }
        } else {
            same = 0;
        }
        last = Some(r);
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}
