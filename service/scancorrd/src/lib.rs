//! # scancorrd — the scancorr sidecar
//!
//! The thin async shell around `scancorr-core`: zenoh I/O, one correction state per machine,
//! the calibration store, liveliness and status. [`run`] takes a configuration and a shutdown
//! future so tests drive the real server.
#![forbid(unsafe_code)]

pub mod config;
mod cost;
mod input;
pub mod latency;
pub mod metrics;
pub mod notify;
mod outgoing;
mod routes;
pub mod server;
mod shard;
mod standby;
pub mod store;
mod uplink;

pub use config::Config;
pub use server::{run, ServiceError};
