//! A Foxglove WebSocket server (ws-protocol, subprotocol `foxglove.websocket.v1`) on
//! localhost, fed with the bus's corrected points and alarms (and, on request, the raw
//! streams): what `scancorr view` serves.
//!
//! Protocol (<https://github.com/foxglove/ws-protocol>, `docs/spec.md`): the client asks for
//! the subprotocol; the server sends `serverInfo`, then `advertise` for every channel (here the
//! `scancorr_bag::foxglove` channels of each machine, as they appear); the client sends
//! `subscribe` / `unsubscribe` with its own subscription ids; each message goes to each
//! subscription as a binary frame: opcode `0x01`, the subscription id (u32 LE), the receive
//! time (u64 LE ns since the epoch) and the protobuf payload. A channel's schema is the base64
//! of the `FileDescriptorSet` that holds it. The machine frame and the nominal scene are
//! latched: a subscription gets the last one at once.
//!
//! Raw streams (`--raw`): each of [`Stream::RAW`] of a machine is a channel whose topic is its
//! bus key (`<prefix>/<machine>/raw/scale`…), schema our own batch message
//! (`scancorr.v1.ScaleBatch`…, from `scancorr_proto::FILE_DESCRIPTOR_SET`); the bus payload is
//! forwarded as it is, undecoded.
//!
//! Threads: zenoh's callbacks only queue the bytes; one thread decodes and encodes; one thread
//! per client reads its requests and writes its queue (a client that falls behind by
//! [`CLIENT_QUEUE`] messages loses the excess, counted and logged). Nothing here runs in
//! scancorrd.

use crate::shared::foxglove::{bus_messages, Nominal};
use anyhow::{Context, Result};
use scancorr_bag::foxglove::{self as fx, Channel};
use scancorr_bag::Stream;
use std::collections::HashMap;
use std::io::ErrorKind;
use std::net::{TcpListener, TcpStream};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::mpsc;
use std::sync::{Arc, Mutex};
use std::time::{Duration, SystemTime, UNIX_EPOCH};
use tungstenite::protocol::Message as WsMessage;

/// The WebSocket subprotocol of Foxglove's ws-protocol.
pub const SUBPROTOCOL: &str = "foxglove.websocket.v1";

/// Messages queued for one client before the excess is dropped.
pub const CLIENT_QUEUE: usize = 1 << 16;

/// What a channel carries: one of the Foxglove channels, or a raw stream as it is on the bus.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
enum Kind {
    Fox(Channel),
    Raw(Stream),
}

impl Kind {
    fn schema_name(self) -> &'static str {
        match self {
            Kind::Fox(c) => c.schema_name(),
            Kind::Raw(s) => s.message_name(),
        }
    }
}

/// The base64 `FileDescriptorSet`s: Foxglove's schemas and ours.
struct Schemas {
    foxglove: String,
    ours: String,
}

struct ChannelInfo {
    id: u32,
    kind: Kind,
    topic: String,
    latched: Option<Vec<u8>>,
}

struct Client {
    tx: mpsc::SyncSender<WsMessage>,
    /// channel id → subscription id.
    subs: HashMap<u32, u32>,
}

#[derive(Default)]
struct Hub {
    channels: Vec<ChannelInfo>,
    /// (machine, kind) → index in `channels`.
    index: HashMap<(String, Kind), usize>,
    clients: HashMap<u64, Client>,
}

fn base64(data: &[u8]) -> String {
    const A: &[u8; 64] = b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";
    let mut s = String::with_capacity(data.len().div_ceil(3) * 4);
    for c in data.chunks(3) {
        let byte = |i: usize| u32::from(*c.get(i).unwrap_or(&0));
        let n = (byte(0) << 16) | (byte(1) << 8) | byte(2);
        for i in 0..4 {
            if i <= c.len() {
                s.push(A[((n >> (18 - 6 * i)) & 63) as usize] as char);
            } else {
                s.push('=');
            }
        }
    }
    s
}

fn advertise(channels: &[&ChannelInfo], schemas: &Schemas) -> WsMessage {
    let list: Vec<serde_json::Value> = channels
        .iter()
        .map(|c| {
            let schema = match c.kind {
                Kind::Fox(_) => &schemas.foxglove,
                Kind::Raw(_) => &schemas.ours,
            };
            serde_json::json!({
                "id": c.id,
                "topic": c.topic,
                "encoding": "protobuf",
                "schemaName": c.kind.schema_name(),
                "schema": schema,
                "schemaEncoding": "protobuf",
            })
        })
        .collect();
    WsMessage::Text(serde_json::json!({"op": "advertise", "channels": list}).to_string())
}

fn now_ns() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| d.as_nanos() as u64)
}

fn frame(sub: u32, t_ns: u64, data: &[u8]) -> WsMessage {
    let mut b = Vec::with_capacity(13 + data.len());
    b.push(0x01);
    b.extend_from_slice(&sub.to_le_bytes());
    b.extend_from_slice(&t_ns.to_le_bytes());
    b.extend_from_slice(data);
    WsMessage::Binary(b)
}

/// The server: channels, clients, and what feeds them.
pub struct Server {
    hub: Arc<Mutex<Hub>>,
    schemas: Arc<Schemas>,
    prefix: String,
    nominal: Option<Nominal>,
    raw: bool,
    points: Vec<fx::CloudPoint>,
    messages: Vec<fx::Message>,
    /// Messages a client lost by falling behind.
    pub dropped: Arc<AtomicU64>,
}

impl Server {
    /// A server for the machines under `prefix`; deviations from `nominal` when given; the
    /// raw streams too when `raw`.
    pub fn new(prefix: &str, nominal: Option<Nominal>, raw: bool) -> Server {
        Server {
            hub: Arc::default(),
            schemas: Arc::new(Schemas {
                foxglove: base64(fx::DESCRIPTOR_SET),
                ours: base64(scancorr_proto::FILE_DESCRIPTOR_SET),
            }),
            prefix: prefix.into(),
            nominal,
            raw,
            points: vec![],
            messages: vec![],
            dropped: Arc::default(),
        }
    }

    /// Listens on `addr` and serves each client on a thread of its own; returns the address.
    pub fn listen(&self, addr: &str) -> Result<std::net::SocketAddr> {
        let listener =
            TcpListener::bind(addr).with_context(|| format!("--port: cannot listen on {addr}"))?;
        let local = listener.local_addr()?;
        let (hub, schema) = (self.hub.clone(), self.schemas.clone());
        let next = Arc::new(AtomicU64::new(1));
        std::thread::Builder::new()
            .name("foxglove-accept".into())
            .spawn(move || {
                for stream in listener.incoming().flatten() {
                    let (hub, schemas) = (hub.clone(), schema.clone());
                    let id = next.fetch_add(1, Ordering::Relaxed);
                    let _ = std::thread::Builder::new()
                        .name(format!("foxglove-client-{id}"))
                        .spawn(move || {
                            if let Err(e) = serve(stream, id, &hub, &schemas) {
                                eprintln!("view: client {id}: {e:#}");
                            }
                            if let Ok(mut h) = hub.lock() {
                                h.clients.remove(&id);
                            }
                        });
                }
            })?;
        Ok(local)
    }

    /// Handles one bus message (`key`, its payload): corrected points and alarms become
    /// Foxglove messages for every subscription, a raw stream's (when asked for) goes as it is.
    /// False when it is none of these, or does not decode.
    pub fn handle(&mut self, key: &str, payload: &[u8]) -> bool {
        let Some((machine, stream)) = Stream::parse_key(&self.prefix, key) else {
            return false;
        };
        let machine = machine.to_string();
        self.messages.clear();
        let raw = self.raw && Stream::RAW.contains(&stream);
        let nominal = self.nominal.as_ref();
        let (points, out) = (&mut self.points, &mut self.messages);
        if !raw && !bus_messages(&machine, stream, payload, nominal, points, out) {
            return false;
        }
        let t0 = self.messages.first().map_or(0, |m| m.t_ns as i64);
        let mut h = match self.hub.lock() {
            Ok(h) => h,
            Err(_) => return false,
        };
        if !h
            .index
            .contains_key(&(machine.clone(), Kind::Fox(Channel::Frame)))
        {
            self.announce(&mut h, &machine, t0);
        }
        let now = now_ns();
        let Hub {
            channels,
            index,
            clients,
        } = &mut *h;
        let mut send = |kind: Kind, data: &[u8]| {
            let Some(&ci) = index.get(&(machine.clone(), kind)) else {
                return;
            };
            let id = channels[ci].id;
            for c in clients.values_mut() {
                if let Some(&sub) = c.subs.get(&id) {
                    if c.tx.try_send(frame(sub, now, data)).is_err() {
                        self.dropped.fetch_add(1, Ordering::Relaxed);
                    }
                }
            }
        };
        if raw {
            send(Kind::Raw(stream), payload);
        }
        for m in &self.messages {
            send(Kind::Fox(m.channel), &m.data);
        }
        true
    }

    /// Advertises `machine`'s channels before any of its messages (so a client can subscribe
    /// before the first point); its frame and nominal scene at time 0.
    pub fn announce_machine(&self, machine: &str) {
        if let Ok(mut h) = self.hub.lock() {
            if !h
                .index
                .contains_key(&(machine.to_string(), Kind::Fox(Channel::Frame)))
            {
                self.announce(&mut h, machine, 0);
            }
        }
    }

    /// A new machine: its channels advertised to every client, frame and nominal latched.
    fn announce(&self, h: &mut Hub, machine: &str, t0: i64) {
        let first = h.channels.len();
        let raw: &[Stream] = if self.raw { &Stream::RAW } else { &[] };
        let kinds = Channel::ALL
            .into_iter()
            .map(Kind::Fox)
            .chain(raw.iter().copied().map(Kind::Raw));
        for kind in kinds {
            let (latched, topic) = match kind {
                Kind::Fox(c @ Channel::Frame) => (
                    Some(fx::frame_message(t0, machine).data),
                    c.topic(&self.prefix, machine),
                ),
                Kind::Fox(c @ Channel::Nominal) => (
                    self.nominal
                        .as_ref()
                        .map(|n| fx::nominal_message(machine, t0, n.scene()).data),
                    c.topic(&self.prefix, machine),
                ),
                Kind::Fox(c) => (None, c.topic(&self.prefix, machine)),
                Kind::Raw(s) => (None, s.key(&self.prefix, machine)),
            };
            let id = h.channels.len() as u32 + 1;
            h.index
                .insert((machine.to_string(), kind), h.channels.len());
            h.channels.push(ChannelInfo {
                id,
                kind,
                topic,
                latched,
            });
        }
        let new: Vec<&ChannelInfo> = h.channels[first..].iter().collect();
        let msg = advertise(&new, &self.schemas);
        for c in h.clients.values() {
            let _ = c.tx.try_send(msg.clone());
        }
    }
}

/// One client: the handshake, `serverInfo` and `advertise`, then its requests and its queue.
fn serve(stream: TcpStream, id: u64, hub: &Mutex<Hub>, schemas: &Schemas) -> Result<()> {
    use tungstenite::handshake::server::{ErrorResponse, Request, Response};
    stream.set_nodelay(true)?;
    let callback = |req: &Request, mut resp: Response| -> Result<Response, ErrorResponse> {
        let asked = req
            .headers()
            .get_all("Sec-WebSocket-Protocol")
            .iter()
            .filter_map(|v| v.to_str().ok())
            .flat_map(|v| v.split(',').map(str::trim))
            .any(|p| p == SUBPROTOCOL);
        if asked {
            resp.headers_mut().insert(
                "Sec-WebSocket-Protocol",
                tungstenite::http::HeaderValue::from_static(SUBPROTOCOL),
            );
        }
        Ok(resp)
    };
    let mut ws = tungstenite::accept_hdr(stream.try_clone()?, callback)
        .map_err(|e| anyhow::anyhow!("handshake: {e}"))?;
    stream.set_read_timeout(Some(Duration::from_millis(5)))?;
    let (tx, rx) = mpsc::sync_channel(CLIENT_QUEUE);
    {
        let mut h = hub.lock().map_err(|_| anyhow::anyhow!("hub poisoned"))?;
        let info = serde_json::json!({
            "op": "serverInfo",
            "name": format!("scancorr view {}", env!("CARGO_PKG_VERSION")),
            "capabilities": [],
            "supportedEncodings": [],
            "metadata": {},
            "sessionId": format!("{}-{id}", std::process::id()),
        });
        let _ = tx.try_send(WsMessage::Text(info.to_string()));
        if !h.channels.is_empty() {
            let all: Vec<&ChannelInfo> = h.channels.iter().collect();
            let _ = tx.try_send(advertise(&all, schemas));
        }
        h.clients.insert(
            id,
            Client {
                tx,
                subs: HashMap::new(),
            },
        );
    }
    loop {
        match ws.read() {
            Ok(WsMessage::Text(t)) => request(&t, id, hub),
            Ok(WsMessage::Close(_)) => return Ok(()),
            Ok(_) => {}
            Err(tungstenite::Error::Io(e))
                if matches!(e.kind(), ErrorKind::WouldBlock | ErrorKind::TimedOut) => {}
            Err(tungstenite::Error::ConnectionClosed | tungstenite::Error::AlreadyClosed) => {
                return Ok(())
            }
            Err(e) => return Err(e.into()),
        }
        let mut wrote = false;
        while let Ok(m) = rx.try_recv() {
            ws.write(m)?;
            wrote = true;
        }
        if wrote {
            ws.flush()?;
        }
    }
}

/// A client's JSON request: `subscribe` / `unsubscribe` (others are ignored, as the
/// capabilities advertised none).
fn request(text: &str, id: u64, hub: &Mutex<Hub>) {
    let Ok(v) = serde_json::from_str::<serde_json::Value>(text) else {
        return;
    };
    let Ok(mut h) = hub.lock() else { return };
    let Hub {
        channels, clients, ..
    } = &mut *h;
    let Some(c) = clients.get_mut(&id) else {
        return;
    };
    match v["op"].as_str() {
        Some("subscribe") => {
            for s in v["subscriptions"].as_array().into_iter().flatten() {
                let (Some(sub), Some(ch)) = (s["id"].as_u64(), s["channelId"].as_u64()) else {
                    continue;
                };
                let Some(info) = channels.iter().find(|c| c.id as u64 == ch) else {
                    continue;
                };
                c.subs.insert(info.id, sub as u32);
                if let Some(l) = &info.latched {
                    let _ = c.tx.try_send(frame(sub as u32, now_ns(), l));
                }
            }
        }
        Some("unsubscribe") => {
            for s in v["subscriptionIds"].as_array().into_iter().flatten() {
                if let Some(sub) = s.as_u64() {
                    c.subs.retain(|_, v| *v as u64 != sub);
                }
            }
        }
        _ => {}
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn base64_pads_like_the_standard() {
        assert_eq!(base64(b""), "");
        assert_eq!(base64(b"f"), "Zg==");
        assert_eq!(base64(b"fo"), "Zm8=");
        assert_eq!(base64(b"foo"), "Zm9v");
        assert_eq!(base64(b"foobar"), "Zm9vYmFy");
        assert_eq!(base64(&[0xff, 0xfe]), "//4=");
    }
}
