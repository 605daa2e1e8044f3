//! How a module talks MQTT: its runtime. The conveyor logic ([`crate::module`]) is the
//! same for every module; a [`Link`] is all that differs:
//!
//! - [`Runtime::Contract`]: a `fb_bridge::client` device (declares, typed will, the
//!   broker's online count);
//! - [`Runtime::Forte`]: what an unmodified 4diac FORTE's MQTT layer does on the wire
//!   (`broker/tests/python/forte_device.py`); the broker knows it from its profile;
//! - [`Runtime::Dinasore`]: what DINASORE's MQTT_PUBLISHER / MQTT_SUBSCRIBER FBs do
//!   (`broker/tests/python/dinasore_device.py`); the broker knows it from its profile.
//!
//! A link publishes the module's outputs ([`Outputs`]) and tells the module what it hears
//! of the other modules ([`Heard`]), each runtime in its own way.

mod contract;
mod dinasore;
mod forte;

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::time::Duration;

use fb_bridge::{Interface, Value};
use tokio::sync::mpsc;

/// How a module talks MQTT.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Runtime {
    Contract,
    Forte,
    Dinasore,
}

impl Runtime {
    pub fn name(self) -> &'static str {
        match self {
            Runtime::Contract => "contract",
            Runtime::Forte => "forte",
            Runtime::Dinasore => "dinasore",
        }
    }

    /// The MQTT keep-alive the module asks for: FORTE hard-codes 20 s, DINASORE's paho
    /// client 60 s (which its publishers never honour); a contract device what it is given.
    pub fn keep_alive(self, configured: Duration) -> Duration {
        match self {
            Runtime::Contract => configured,
            Runtime::Forte => forte::KEEP_ALIVE,
            Runtime::Dinasore => dinasore::KEEP_ALIVE,
        }
    }

    /// Whether the module publishes the event STATE carrying all its outputs (contract,
    /// FORTE: a PUBLISH_6), or its data outputs one by one (DINASORE: one publisher FB per
    /// value, which cannot send an event with several values).
    pub fn publishes_state(self) -> bool {
        self != Runtime::Dinasore
    }
}

/// Every module of the run and its runtime: the line's engineering, known to every module
/// (a FORTE or DINASORE application names its peers' topics in its configuration).
pub type Roster = BTreeMap<String, Runtime>;

/// Where the broker is and what the line is called.
#[derive(Debug, Clone)]
pub struct Setup {
    pub host: String,
    pub port: u16,
    /// The keep-alive of contract modules.
    pub keep_alive: Duration,
    /// The broker's `[broker] line`: FORTE modules read `fbbus/lines/<line>/online`.
    pub line: String,
}

/// The bound on opening a link and on every wait inside it.
pub const TIMEOUT: Duration = Duration::from_secs(10);
/// How long a clean stop waits for the runtime's connections to end.
const CLOSE_WAIT: Duration = Duration::from_secs(2);

/// Where FORTE and DINASORE modules publish their outputs: `line1/<id>/<port>`, each
/// topic mapped onto a port by the module's profile.
const OWN_TOPICS: &str = "line1";

/// `CONV` of a module that publishes STATE: contract modules declare it, a FORTE module's
/// profile gives it.
pub const STATE_INTERFACE: &str = r#"{"fbs": {"CONV": {
    "type": "CONVEYOR",
    "events_out": {"STATE": {"with": ["ID", "CONNECT", "SENSOR_IN", "SENSOR_OUT", "POSITION", "SWAP"]}},
    "data_out": {"ID": "STRING", "CONNECT": "BOOL", "SENSOR_IN": "BOOL",
                 "SENSOR_OUT": "BOOL", "POSITION": "INT", "SWAP": "BOOL"}
}}}"#;

/// `CONV` of a DINASORE module, from its profile: data outputs only.
pub const DATA_INTERFACE: &str = r#"{"fbs": {"CONV": {
    "type": "CONVEYOR",
    "data_out": {"CONNECT": "BOOL", "SENSOR_IN": "BOOL", "SENSOR_OUT": "BOOL",
                 "POSITION": "INT", "SWAP": "BOOL"}
}}}"#;

/// The data outputs a DINASORE module publishes, one publisher FB (and connection) each.
const DATA_PORTS: [&str; 5] = ["CONNECT", "SENSOR_IN", "SENSOR_OUT", "POSITION", "SWAP"];

/// The interface of a module of this runtime.
pub fn interface(runtime: Runtime) -> Interface {
    let text = match runtime.publishes_state() {
        true => STATE_INTERFACE,
        false => DATA_INTERFACE,
    };
    serde_json::from_str(text).expect("the example's interfaces are valid")
}

/// The ports a module follows on a peer of `runtime`: its STATE, or the data outputs that
/// matter to the line when it has no STATE; and its CONNECT, which its will sets FALSE.
fn followed_ports(runtime: Runtime) -> &'static [&'static str] {
    match runtime.publishes_state() {
        true => &["STATE", "CONNECT"],
        false => &["POSITION", "SENSOR_OUT", "SWAP", "CONNECT"],
    }
}

/// What the module outputs (CONNECT is TRUE while it runs; ID is its id).
#[derive(Debug, Clone, Copy)]
pub struct Outputs {
    pub sensor_in: bool,
    pub sensor_out: bool,
    pub position: i16,
    pub swap: bool,
}

/// What a link heard, for the module.
#[derive(Debug)]
pub enum Heard {
    /// A peer's message: what it says about the peer (`None`: not in this message).
    Peer(String, PeerUpdate),
    /// The broker's online count of the line.
    Count(u64),
}

#[derive(Debug, Default)]
pub struct PeerUpdate {
    pub connect: Option<bool>,
    pub position: Option<i16>,
    pub sensor_out: Option<bool>,
    pub swap: Option<bool>,
}

impl PeerUpdate {
    /// What typed values received on a peer's `port` say; a value of another type than
    /// expected is ignored.
    fn from_values(port: &str, values: &[Value]) -> PeerUpdate {
        let bool_at = |i: usize| match values.get(i) {
            Some(Value::Bool(b)) => Some(*b),
            _ => None,
        };
        let int_at = |i: usize| match values.get(i) {
            Some(Value::Int(n)) => Some(*n),
            _ => None,
        };
        match port {
            // WITH order: ID, CONNECT, SENSOR_IN, SENSOR_OUT, POSITION, SWAP.
            "STATE" => PeerUpdate {
                sensor_out: bool_at(3),
                position: int_at(4),
                swap: bool_at(5),
                ..PeerUpdate::default()
            },
            "POSITION" => PeerUpdate {
                position: int_at(0),
                ..PeerUpdate::default()
            },
            "SENSOR_OUT" => PeerUpdate {
                sensor_out: bool_at(0),
                ..PeerUpdate::default()
            },
            "SWAP" => PeerUpdate {
                swap: bool_at(0),
                ..PeerUpdate::default()
            },
            "CONNECT" => PeerUpdate {
                connect: bool_at(0),
                ..PeerUpdate::default()
            },
            _ => PeerUpdate::default(),
        }
    }
}

/// A module's connection(s) to the broker, by runtime.
pub enum Link {
    Contract(contract::Link),
    Forte(forte::Link),
    Dinasore(dinasore::Link),
}

impl Link {
    /// INIT: connects module `id` and starts following the other modules of `roster`;
    /// what it hears goes to `heard`.
    pub async fn open(
        runtime: Runtime,
        id: &str,
        setup: &Setup,
        roster: &Roster,
        heard: mpsc::Sender<Heard>,
    ) -> Result<Link, String> {
        let peers: Vec<(String, Runtime)> = roster
            .iter()
            .filter(|(peer, _)| *peer != id)
            .map(|(peer, runtime)| (peer.clone(), *runtime))
            .collect();
        Ok(match runtime {
            Runtime::Contract => {
                Link::Contract(contract::Link::open(id, setup, peers, heard).await?)
            }
            Runtime::Forte => Link::Forte(forte::Link::open(id, setup, &peers, heard).await?),
            Runtime::Dinasore => {
                Link::Dinasore(dinasore::Link::open(id, setup, &peers, heard).await?)
            }
        })
    }

    /// Whether the module counts the online modules itself, from their CONNECT messages
    /// (as the reference study's NUM_DEV block did): a DINASORE subscriber reads
    /// `float(json[NAME])`, which the broker's plain-number count is not.
    pub fn counts_itself(&self) -> bool {
        matches!(self, Link::Dinasore(_))
    }

    /// Publishes CONNECT = TRUE and the outputs.
    pub async fn publish(&mut self, id: &str, outputs: &Outputs) -> Result<(), String> {
        match self {
            Link::Contract(link) => link.publish(id, outputs).await,
            Link::Forte(link) => link.publish(id, outputs).await,
            Link::Dinasore(link) => link.publish(outputs).await,
        }
    }

    /// INIT-: the runtime's own clean stop.
    pub async fn close(&mut self) {
        match self {
            Link::Contract(link) => link.close().await,
            Link::Forte(link) => link.close().await,
            Link::Dinasore(link) => link.close().await,
        }
    }
}

/// The profile the broker needs for module `id` of `runtime` (TOML, `docs/runtimes.md`),
/// `None` for a contract module, which declares itself.
pub fn profile(id: &str, runtime: Runtime) -> Option<String> {
    let mut t = String::new();
    match runtime {
        Runtime::Contract => return None,
        Runtime::Forte => {
            let _ = write!(
                t,
                "# {id} as an unmodified 4diac FORTE device (written by the conveyor example).\n\
                 # Its PUBLISH FBs' IDs: fbdk[].mqtt[tcp://<broker>, {id}, {OWN_TOPICS}/{id}/state]\n\
                 # (PUBLISH_6, CONV.STATE) and fbdk[].mqtt[tcp://<broker>, {id}, {OWN_TOPICS}/{id}/connect]\n\
                 # (PUBLISH_1, CONV.CONNECT). It reads its peers on fbdk/<peer>/CONV/<PORT> and the\n\
                 # line's online count on fbbus/lines/<line>/online (raw[].mqtt[], a STRING).\n\
                 device = \"{id}\"\n\
                 runtime = \"forte\"\n\n\
                 [identity]\n\
                 client_id = \"{id}\"\n\n\
                 [speaks]\n\
                 encoding = \"fbdk\"\n\
                 fbdk_time_unit = \"ns\"\n\
                 max_payload = 255\n\n\
                 [interface.fbs.CONV]\n\
                 type = \"CONVEYOR\"\n\
                 events_out = {{ STATE = {{ with = [\"ID\", \"CONNECT\", \"SENSOR_IN\", \"SENSOR_OUT\", \"POSITION\", \"SWAP\"] }} }}\n\
                 data_out = {{ ID = \"STRING\", CONNECT = \"BOOL\", SENSOR_IN = \"BOOL\", SENSOR_OUT = \"BOOL\", POSITION = \"INT\", SWAP = \"BOOL\" }}\n"
            );
            for port in ["STATE", "CONNECT"] {
                own_topic(&mut t, id, port);
            }
        }
        Runtime::Dinasore => {
            let _ = write!(
                t,
                "# {id} as an unmodified DINASORE device (written by the conveyor example): one\n\
                 # MQTT_PUBLISHER FB per output, {{\"<PORT>\": \"<str(value)>\"}} on {OWN_TOPICS}/{id}/<port>,\n\
                 # random client ids, no username, no will. It reads its peers on\n\
                 # dinasore/<peer>/CONV/<PORT> (MQTT_SUBSCRIBER: float(json[NAME])).\n\
                 device = \"{id}\"\n\
                 runtime = \"dinasore\"\n\n\
                 [identity]\n\
                 topics_only = true\n\n\
                 [speaks]\n\
                 encoding = \"dinasore\"\n\
                 string_numbers = true\n\
                 enforce_keep_alive = false\n\n\
                 [interface.fbs.CONV]\n\
                 type = \"CONVEYOR\"\n\
                 data_out = {{ CONNECT = \"BOOL\", SENSOR_IN = \"BOOL\", SENSOR_OUT = \"BOOL\", POSITION = \"INT\", SWAP = \"BOOL\" }}\n"
            );
            for port in DATA_PORTS {
                own_topic(&mut t, id, port);
            }
        }
    }
    t.push_str(
        "\n# Its runtime sets no will: the broker publishes this on fb/<id>/CONV/CONNECT when\n\
         # the device goes offline.\n\
         [will]\n\
         \"CONV.CONNECT\" = false\n\n\
         # The line counts its modules from CONNECT (NUM_DEV): every departure, a clean\n\
         # DISCONNECT too, must say CONNECT = FALSE (an MQTT will would not).\n\
         [liveness]\n\
         will_on_clean_disconnect = true\n",
    );
    Some(t)
}

/// The own topic of module `id`'s output `port`.
fn own_topic_name(id: &str, port: &str) -> String {
    format!("{OWN_TOPICS}/{id}/{}", port.to_ascii_lowercase())
}

fn own_topic(t: &mut String, id: &str, port: &str) {
    let _ = write!(
        t,
        "\n[[topics]]\ntopic = \"{}\"\nport = \"CONV.{port}\"\n",
        own_topic_name(id, port)
    );
}
