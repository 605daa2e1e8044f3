//! # fbbus-loadtest: throughput, latency and loss of any MQTT broker
//!
//! The harness reproduces the JMeter study of an MQTT-connected IEC 61499 conveyor line
//! (`stress`, `loss-search`, `perf`) and goes beyond it (`fan-in`, `fan-out`, `pairs`,
//! `bridge`, `idle`, `storm`, `conveyor`, and the network campaigns `mutate` and `churn`), against fbbus or any other MQTT 3.1.1/5 broker, alone or
//! two brokers interleaved (compare mode). See `loadtest/README.md` for every scenario,
//! parameter and output.
//!
//! **It owns** the load scenarios, the broker processes it starts and the reports. **It
//! must not know** a broker's internals: it drives every broker, fbbus included, as a
//! process over MQTT and HTTP, so its figures compare like with like.
//!
//! How a number is made, in one pass:
//! - [`rig`]: publishers and subscribers connected once per broker; a *batch* sends `n`
//!   messages per publisher (a burst, or at a rate) and waits until every copy arrived,
//!   nothing arrived for the quiet time, or the batch limit;
//! - [`message`]: each message is an fbbus event `{"seq":N,"ts":T}` padded to size, so
//!   fbbus type-checks it like a device's and any broker carries it;
//! - [`tally`]: each subscriber counts distinct deliveries, duplicates, order and
//!   latency (HDR histogram) per batch; [`clock`]: one process, one clock;
//! - [`contract`]: on fbbus, publishers declare themselves and an FB subscriber (the
//!   fb-bridge client API) counts typed INDs where the study counted them;
//! - [`session`] and [`scenario`]: the scenarios run batches, A B A B in compare mode;
//!   [`run`](mod@run) assembles the [`model::Report`]; [`report`] writes the table, JSON, CSV,
//!   JTL and SVG charts from it;
//! - [`sink`]: the trivial in-process sink that measures the harness's own ceiling;
//! - the network campaigns `mutate` and `churn` ([`scenario::campaign`]) speak raw MQTT
//!   ([`wire`]: packets and mutations byte by byte) from seeded generators ([`rng`]),
//!   and read the broker's process ([`broker_process`]) and metrics ([`scrape`]);
//! - `compare` (in the binary) starts fbbus, Mosquitto and raw rumqttd as child
//!   processes ([`broker_process::spawn`]) and runs the earlier broker study's scenarios
//!   against each, bursts on raw sockets ([`raw_client`]), connections through
//!   [`scenario::connections`].

pub mod broker_process;
pub mod client;
pub mod clock;
pub mod contract;
pub mod machine;
pub mod message;
pub mod model;
pub mod raw_client;
pub mod relay;
pub mod report;
pub mod rig;
pub mod rng;
pub mod run;
pub mod scenario;
pub mod scrape;
pub mod session;
pub mod sink;
pub mod tally;
pub mod target;
pub mod wire;
pub mod zenoh_floor;

pub use run::{run, Plan};

/// Everything that can stop a run, each saying what to check.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    #[error("target {0}")]
    Target(String),
    #[error("cannot connect {id} to {address}: {reason} (is the broker running there?)")]
    Connect {
        id: String,
        address: String,
        reason: String,
    },
    #[error("{address} refused {id}: {reason} (check --username, the password in MQTT_PASSWORD or --password-file, and the broker's access rules)")]
    Refused {
        id: String,
        address: String,
        reason: String,
    },
    #[error("{id} on {address}: {reason}")]
    Closed {
        id: String,
        address: String,
        reason: String,
    },
    #[error("timed out after {waited:?} waiting for {what}")]
    Timeout {
        waited: std::time::Duration,
        what: String,
    },
    #[error("fbbus device contract: {0}")]
    Contract(String),
    /// A broker process the harness starts itself (`compare`).
    #[error("{0}")]
    Process(String),
    #[error("{0}")]
    Io(#[from] std::io::Error),
}
