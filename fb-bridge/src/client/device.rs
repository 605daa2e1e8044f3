//! The device: one connection, its declaration, and the INIT of its communication FBs.

use std::sync::atomic::Ordering;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use rumqttc::{AsyncClient, LastWill, MqttOptions, QoS};
use serde::Deserialize;
use tokio::sync::{broadcast, mpsc, oneshot, watch};
use tokio::task::JoinHandle;

use super::connection::{self, Shared, Sink};
use super::{valid_device_id, ClientError, Diagnostic, PortTypes, Publisher, Subscriber};
use crate::codec::json::value_to_json;
use crate::interface::{Interface, OutputPort};
use crate::topic;
use crate::value::Value;

/// Requests (publishes, subscribes) that may wait for the connection at once.
const REQUEST_QUEUE: usize = 1024;

/// Largest packet sent or accepted; the broker enforces its own (64 KiB by default).
const MAX_PACKET: usize = 16 << 20;

/// Messages a subscriber may have unread before the connection waits for it (and, if it
/// does not read, drops new ones: `connection::Shared::deliver`).
pub(super) const IND_QUEUE: usize = 1024;

/// How to reach the broker and who the device is.
#[derive(Debug, Clone)]
pub struct DeviceConfig {
    pub host: String,
    pub port: u16,
    /// The device id: MQTT client id, and username when `password` is set.
    pub id: String,
    pub password: Option<String>,
    /// MQTT keep-alive: 0 or at least one second. The broker declares the device lost
    /// after 1.5 times this without a packet.
    pub keep_alive: Duration,
    /// What the broker publishes for the device when its connection ends without
    /// DISCONNECT.
    pub will: Option<WillSpec>,
    /// The bound on every wait: the declaration's answer, PUBACKs, SUBACKs, registry
    /// records.
    pub timeout: Duration,
}

impl DeviceConfig {
    /// Anonymous, keep-alive 5 s, no will, 5 s timeout.
    pub fn new(host: impl Into<String>, port: u16, id: impl Into<String>) -> DeviceConfig {
        DeviceConfig {
            host: host.into(),
            port,
            id: id.into(),
            password: None,
            keep_alive: Duration::from_secs(5),
            will: None,
            timeout: Duration::from_secs(5),
        }
    }
}

/// A will on one of the device's data outputs: `fb/<id>/<fb>/<port>` set to `value`
/// (canonical JSON, QoS 1, not retained) when the device dies. The broker checks it like
/// any publication on that port.
#[derive(Debug, Clone, PartialEq)]
pub struct WillSpec {
    pub fb: String,
    pub port: String,
    pub value: Value,
}

impl WillSpec {
    pub fn new(fb: impl Into<String>, port: impl Into<String>, value: Value) -> WillSpec {
        WillSpec {
            fb: fb.into(),
            port: port.into(),
            value,
        }
    }

    /// The will's topic and payload, checked against the interface.
    fn message(&self, id: &str, interface: &Interface) -> Result<(String, String), ClientError> {
        let port = format!("{}.{}", self.fb, self.port);
        let Some(OutputPort::Data(ty)) = interface.output(&self.fb, &self.port) else {
            return Err(ClientError::InvalidConfig(format!(
                "will: {port} is not a data output of the interface"
            )));
        };
        self.value
            .check(ty)
            .map_err(|e| ClientError::InvalidConfig(format!("will: {port}: {e}")))?;
        Ok((
            format!("fb/{id}/{}/{}", self.fb, self.port),
            value_to_json(&self.value).to_string(),
        ))
    }
}

/// A connected device. See the [module documentation](super).
///
/// Its methods take `&self`, so one device can be shared between tasks (`Arc<Device>`);
/// the connection ends abruptly when the last handle is dropped without
/// [`Device::disconnect`].
pub struct Device {
    shared: Arc<Shared>,
    interface: Interface,
    /// The connection task, until INIT-.
    task: Mutex<Option<JoinHandle<()>>>,
}

impl Device {
    /// INIT+: connects, subscribes to the device's diag topic, declares `interface` and
    /// waits for the broker's answer. Returns with QO = TRUE, or the reason it could not
    /// (connection refused, declaration refused with every mistake, timeout).
    pub async fn connect(
        config: DeviceConfig,
        interface: Interface,
    ) -> Result<Device, ClientError> {
        let options = mqtt_options(&config, &interface)?;
        let declaration = serde_json::to_vec(&interface).expect("an interface serializes");
        let (client, mut eventloop) = AsyncClient::new(options, REQUEST_QUEUE);
        eventloop
            .network_options
            .set_connection_timeout(config.timeout.as_secs().max(1));
        // Without it an IND -> REQ chain waits for the broker's delayed ACK of the PUBACK
        // (Nagle): 44 ms per hop instead of 0.6 ms, measured on loopback.
        eventloop.network_options.set_tcp_nodelay(true);
        let shared = Arc::new(Shared::new(
            config.id,
            client,
            config.timeout,
            connection::reader_wait(config.keep_alive),
            declaration,
        ));
        let mut answers = shared.diagnostics.subscribe();
        let (first_tx, mut first_rx) = oneshot::channel();
        let task = tokio::spawn(connection::run(eventloop, shared.clone(), first_tx));
        let device = Device {
            shared,
            interface,
            task: Mutex::new(Some(task)),
        };

        let answer = tokio::time::timeout(config.timeout, async {
            let mut first_done = false;
            loop {
                tokio::select! {
                    first = &mut first_rx, if !first_done => match first {
                        Ok(Err(e)) => return Err(e),
                        _ => first_done = true,
                    },
                    answer = answers.recv() => match answer {
                        Ok(Diagnostic::Declared { .. }) => return Ok(()),
                        Ok(Diagnostic::DeclarationRefused { errors }) => {
                            return Err(ClientError::Declaration(errors.join("; ")))
                        }
                        Ok(_) | Err(broadcast::error::RecvError::Lagged(_)) => {}
                        Err(broadcast::error::RecvError::Closed) => return Err(ClientError::Closed),
                    },
                }
            }
        })
        .await
        .unwrap_or(Err(ClientError::Timeout {
            waited: config.timeout,
            what: "answer to the declaration",
        }));
        match answer {
            Ok(()) => Ok(device),
            Err(e) => {
                device.disconnect().await;
                Err(e)
            }
        }
    }

    pub fn id(&self) -> &str {
        &self.shared.id
    }

    /// The interface this device declared.
    pub fn interface(&self) -> &Interface {
        &self.interface
    }

    /// INITO: (QO, STATUS). `(true, "OK")` while connected and declared; otherwise why not
    /// (`reconnecting: ...`, `declaring`, `declaration refused: ...`, `disconnected`).
    pub fn status(&self) -> (bool, String) {
        self.shared.status.borrow().clone()
    }

    /// Follows [`Device::status`].
    pub fn status_changes(&self) -> watch::Receiver<(bool, String)> {
        self.shared.status.subscribe()
    }

    /// The broker's session number of the current connection (from the latest
    /// declaration answer).
    pub fn session(&self) -> u64 {
        self.shared.session_and_line().0
    }

    /// The line the broker serves (from the latest declaration answer).
    pub fn line(&self) -> String {
        self.shared.session_and_line().1
    }

    /// Everything the broker says on the diag topic from now on: declaration answers and
    /// refused publications.
    pub fn diagnostics(&self) -> broadcast::Receiver<Diagnostic> {
        self.shared.diagnostics.subscribe()
    }

    /// The last 32 diag messages, oldest first.
    pub fn recent_diagnostics(&self) -> Vec<Diagnostic> {
        self.shared.recent_diagnostics()
    }

    /// INIT of a PUBLISH FB on the output port `fb.port` (an event output or a data
    /// output of this device's interface).
    pub fn publisher(&self, fb: &str, port: &str) -> Result<Publisher, ClientError> {
        let types = self
            .interface
            .output(fb, port)
            .ok_or_else(|| ClientError::NotAnOutput {
                device: self.shared.id.clone(),
                fb: fb.to_owned(),
                port: port.to_owned(),
            })?;
        Ok(Publisher::new(
            self.shared.clone(),
            fb,
            port,
            PortTypes::of(&types),
        ))
    }

    /// INIT of a SUBSCRIBE FB on another device's output port `device.fb.port`. The port's
    /// types come from the device's registry record (`fbbus/devices/<device>`); it must
    /// have declared within [`DeviceConfig::timeout`]. Returns once the broker has granted
    /// the subscription, so every message published after this returns is delivered.
    ///
    /// The types are those of the declaration current at INIT; if the remote device
    /// re-declares the port with another type, INIT a new subscriber.
    pub async fn subscriber(
        &self,
        device: &str,
        fb: &str,
        port: &str,
    ) -> Result<Subscriber, ClientError> {
        let interface = self.registry_interface(device).await?;
        let types = interface
            .output(fb, port)
            .ok_or_else(|| ClientError::NotAnOutput {
                device: device.to_owned(),
                fb: fb.to_owned(),
                port: port.to_owned(),
            })?;
        let topic = format!("fb/{device}/{fb}/{port}");
        let (tx, rx) = mpsc::channel(IND_QUEUE);
        let route = self.shared.add_route(&topic, Sink::Queue(tx));
        self.shared.subscribe_confirmed(&topic).await?;
        Ok(Subscriber::new(topic, PortTypes::of(&types), route, rx))
    }

    /// The interface in `device`'s retained registry record.
    async fn registry_interface(&self, device: &str) -> Result<Interface, ClientError> {
        #[derive(Deserialize)]
        struct Record {
            interface: Interface,
        }
        if !valid_device_id(device) {
            return Err(ClientError::UnknownDevice(device.to_owned()));
        }
        let topic = topic::device_record(device);
        let (tx, mut rx) = mpsc::channel(4);
        let _route = self.shared.add_route(&topic, Sink::Queue(tx));
        self.shared.subscribe_confirmed(&topic).await?;
        let record = tokio::time::timeout(self.shared.timeout, async {
            while let Some(publish) = rx.recv().await {
                match serde_json::from_slice::<Record>(&publish.payload) {
                    Ok(record) => return Some(record.interface),
                    Err(e) => tracing::warn!(topic, error = %e, "unreadable registry record"),
                }
            }
            None
        })
        .await;
        record
            .ok()
            .flatten()
            .ok_or_else(|| ClientError::UnknownDevice(device.to_owned()))
    }

    /// Follows the number of online devices of `line` (usually [`Device::line`]), the
    /// broker's retained `fbbus/lines/<line>/online`: this replaces a NUM_DEV block.
    /// Returns once the current count has arrived.
    pub async fn online_count(&self, line: &str) -> Result<watch::Receiver<u64>, ClientError> {
        if line.is_empty() || line.contains(['/', '+', '#']) {
            return Err(ClientError::InvalidConfig(format!("line name {line:?}")));
        }
        let topic = topic::line_online(line);
        let (tx, mut rx) = watch::channel(0);
        let route = self
            .shared
            .add_route(&topic, Sink::Count { tx, first: true });
        self.shared.subscribe_confirmed(&topic).await?;
        match tokio::time::timeout(self.shared.timeout, rx.changed()).await {
            Ok(Ok(())) => {}
            Ok(Err(_)) => return Err(ClientError::Closed),
            Err(_) => {
                return Err(ClientError::Timeout {
                    waited: self.shared.timeout,
                    what: "online count",
                })
            }
        }
        rx.borrow_and_update();
        // The connection task drops the route once every receiver is gone.
        route.keep();
        Ok(rx)
    }

    /// INIT-: a clean DISCONNECT (the broker publishes no will). Afterwards the status is
    /// QO = FALSE, `disconnected`, and every publisher and subscriber of this device
    /// reports [`ClientError::Closed`] or ends. REQs still waiting for their CNF end with
    /// an error.
    pub async fn disconnect(&self) {
        let task = self.task.lock().unwrap_or_else(|p| p.into_inner()).take();
        let Some(mut task) = task else {
            return;
        };
        self.shared.closing.store(true, Ordering::Relaxed);
        let sent = tokio::time::timeout(self.shared.timeout, self.shared.client.disconnect())
            .await
            .is_ok_and(|r| r.is_ok());
        if !sent
            || tokio::time::timeout(self.shared.timeout, &mut task)
                .await
                .is_err()
        {
            task.abort();
        }
    }
}

impl Drop for Device {
    /// Without [`Device::disconnect`], the connection just ends: the broker publishes the
    /// will.
    fn drop(&mut self) {
        let task = self
            .task
            .get_mut()
            .unwrap_or_else(|p| p.into_inner())
            .take();
        if let Some(task) = task {
            task.abort();
        }
    }
}

fn mqtt_options(config: &DeviceConfig, interface: &Interface) -> Result<MqttOptions, ClientError> {
    if !valid_device_id(&config.id) {
        return Err(ClientError::InvalidConfig(format!(
            "device id {:?}: not empty, without '/', '+', '#' or '$'",
            config.id
        )));
    }
    if !config.keep_alive.is_zero() && config.keep_alive < Duration::from_secs(1) {
        return Err(ClientError::InvalidConfig(
            "keep-alive: 0 or at least one second".into(),
        ));
    }
    let mut options = MqttOptions::new(&config.id, &config.host, config.port);
    options
        .set_keep_alive(config.keep_alive)
        .set_clean_session(true)
        .set_max_packet_size(MAX_PACKET, MAX_PACKET);
    if let Some(password) = &config.password {
        options.set_credentials(&config.id, password);
    }
    if let Some(will) = &config.will {
        let (topic, payload) = will.message(&config.id, interface)?;
        options.set_last_will(LastWill::new(topic, payload, QoS::AtLeastOnce, false));
    }
    Ok(options)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn conveyor() -> Interface {
        serde_json::from_str(
            r#"{"fbs": {"CONV": {
                "events_out": {"STATE": {"with": ["CONNECT"]}},
                "data_out": {"CONNECT": "BOOL", "POSITION": "INT"}}}}"#,
        )
        .unwrap()
    }

    #[test]
    fn a_will_is_a_checked_value_on_a_data_output() {
        let will = WillSpec::new("CONV", "CONNECT", Value::Bool(false));
        assert_eq!(
            will.message("conveyor-a", &conveyor()),
            Ok(("fb/conveyor-a/CONV/CONNECT".into(), "false".into()))
        );
        for (fb, port, value, expect) in [
            ("CONV", "STATE", Value::Bool(false), "not a data output"),
            ("CONV", "NOPE", Value::Bool(false), "not a data output"),
            (
                "CONV",
                "POSITION",
                Value::Bool(false),
                "CONV.POSITION: expected INT",
            ),
        ] {
            let error = WillSpec::new(fb, port, value)
                .message("conveyor-a", &conveyor())
                .unwrap_err()
                .to_string();
            assert!(error.contains(expect), "{error}");
        }
    }

    #[test]
    fn ids_and_keep_alives_that_cannot_work_are_refused() {
        for id in ["", "a/b", "a+", "#", "$SYS"] {
            let config = DeviceConfig::new("localhost", 1883, id);
            assert!(matches!(
                mqtt_options(&config, &conveyor()),
                Err(ClientError::InvalidConfig(_))
            ));
        }
        let mut config = DeviceConfig::new("localhost", 1883, "conveyor-a");
        config.keep_alive = Duration::from_millis(500);
        assert!(mqtt_options(&config, &conveyor()).is_err());
        config.keep_alive = Duration::ZERO;
        config.password = Some("secret".into());
        let options = mqtt_options(&config, &conveyor()).unwrap();
        let login = options.credentials().expect("credentials");
        assert_eq!(
            (login.username.as_str(), login.password.as_str()),
            ("conveyor-a", "secret")
        );
    }

    #[tokio::test]
    async fn an_unreachable_broker_fails_init_quickly() {
        // A port nobody listens on: bound, then released.
        let port = std::net::TcpListener::bind("127.0.0.1:0")
            .unwrap()
            .local_addr()
            .unwrap()
            .port();
        let started = std::time::Instant::now();
        let result = Device::connect(
            DeviceConfig::new("127.0.0.1", port, "conveyor-a"),
            conveyor(),
        )
        .await;
        assert!(
            matches!(result, Err(ClientError::Connect(_))),
            "{:?}",
            result.err()
        );
        assert!(started.elapsed() < Duration::from_secs(2));
    }
}
