//! rumqttc clients (MQTT 3.1.1 and 5) whose event loop runs in a task and whose incoming
//! packets arrive on a channel, so a test reads them in order with a timeout.
#![allow(dead_code)]

use std::time::Duration;

use tokio::sync::mpsc;
use tokio::task::JoinHandle;

pub const WAIT: Duration = Duration::from_secs(5);

/// An MQTT 3.1.1 client.
pub struct V4 {
    pub client: rumqttc::AsyncClient,
    incoming: mpsc::UnboundedReceiver<rumqttc::Packet>,
    task: JoinHandle<()>,
}

impl V4 {
    pub fn options(port: u16, id: &str, login: Option<(&str, &str)>) -> rumqttc::MqttOptions {
        let mut o = rumqttc::MqttOptions::new(id, "127.0.0.1", port);
        o.set_keep_alive(Duration::from_secs(30));
        if let Some((u, p)) = login {
            o.set_credentials(u, p);
        }
        o
    }

    pub async fn connect(port: u16, id: &str, login: Option<(&str, &str)>) -> Result<V4, String> {
        V4::connect_with(V4::options(port, id, login)).await
    }

    /// Connects and waits for CONNACK; Err carries the refusal (e.g. "BadUserNamePassword").
    pub async fn connect_with(options: rumqttc::MqttOptions) -> Result<V4, String> {
        let (client, mut eventloop) = rumqttc::AsyncClient::new(options, 100);
        loop {
            match tokio::time::timeout(WAIT, eventloop.poll()).await {
                Ok(Ok(rumqttc::Event::Incoming(rumqttc::Packet::ConnAck(_)))) => break,
                Ok(Ok(_)) => continue,
                Ok(Err(rumqttc::ConnectionError::ConnectionRefused(code))) => {
                    return Err(format!("{code:?}"))
                }
                Ok(Err(e)) => return Err(format!("{e}")),
                Err(_) => return Err("timeout".into()),
            }
        }
        let (tx, incoming) = mpsc::unbounded_channel();
        let task = tokio::spawn(async move {
            while let Ok(event) = eventloop.poll().await {
                if let rumqttc::Event::Incoming(packet) = event {
                    if tx.send(packet).is_err() {
                        return;
                    }
                }
            }
        });
        Ok(V4 {
            client,
            incoming,
            task,
        })
    }

    /// The next incoming packet matching `pick`, skipping others; None after `within`.
    pub async fn next<T>(
        &mut self,
        within: Duration,
        mut pick: impl FnMut(rumqttc::Packet) -> Option<T>,
    ) -> Option<T> {
        let deadline = tokio::time::Instant::now() + within;
        loop {
            let packet = tokio::time::timeout_at(deadline, self.incoming.recv())
                .await
                .ok()??;
            if let Some(t) = pick(packet) {
                return Some(t);
            }
        }
    }

    pub async fn next_publish(&mut self, within: Duration) -> Option<rumqttc::Publish> {
        self.next(within, |p| match p {
            rumqttc::Packet::Publish(p) => Some(p),
            _ => None,
        })
        .await
    }

    /// Declares `interface` for device `id` as a device does (the one declare-a-device
    /// of the tests over rumqttc): subscribes to `fbbus/diag/<id>`, publishes the
    /// declaration at QoS 1 and waits for the broker's answer there, which must be ok.
    pub async fn declare(&mut self, id: &str, interface: &str) {
        self.subscribe(&format!("fbbus/diag/{id}")).await;
        self.client
            .publish(
                format!("fbbus/declare/{id}"),
                rumqttc::QoS::AtLeastOnce,
                false,
                interface,
            )
            .await
            .unwrap();
        let answer = self.next_publish(WAIT).await.expect("declaration answer");
        let answer: serde_json::Value = serde_json::from_slice(&answer.payload).unwrap();
        assert_eq!(answer["ok"], true, "declaration of {id}: {answer}");
    }

    pub async fn subscribe(&mut self, filter: &str) -> Vec<rumqttc::SubscribeReasonCode> {
        self.client
            .subscribe(filter, rumqttc::QoS::AtLeastOnce)
            .await
            .unwrap();
        self.next(WAIT, |p| match p {
            rumqttc::Packet::SubAck(s) => Some(s.return_codes),
            _ => None,
        })
        .await
        .expect("SUBACK")
    }

    /// Whether the event loop is still running (false once the broker closed the connection).
    pub fn alive(&self) -> bool {
        !self.task.is_finished()
    }
}

impl Drop for V4 {
    fn drop(&mut self) {
        self.task.abort();
    }
}

pub use rumqttc::v5::mqttbytes::v5 as p5;

/// An MQTT 5 client.
pub struct V5 {
    pub client: rumqttc::v5::AsyncClient,
    /// Packets, then the error that ended the event loop. rumqttc's v5 client ends its
    /// connection on a refused SUBACK/PUBACK/PUBREC code and reports the code only there.
    incoming: mpsc::UnboundedReceiver<Result<p5::Packet, String>>,
    task: JoinHandle<()>,
}

impl V5 {
    pub fn options(port: u16, id: &str, login: Option<(&str, &str)>) -> rumqttc::v5::MqttOptions {
        let mut o = rumqttc::v5::MqttOptions::new(id, "127.0.0.1", port);
        o.set_keep_alive(Duration::from_secs(30));
        if let Some((u, p)) = login {
            o.set_credentials(u, p);
        }
        o
    }

    pub async fn connect(port: u16, id: &str, login: Option<(&str, &str)>) -> Result<V5, String> {
        V5::connect_with(V5::options(port, id, login)).await
    }

    pub async fn connect_with(options: rumqttc::v5::MqttOptions) -> Result<V5, String> {
        let (client, mut eventloop) = rumqttc::v5::AsyncClient::new(options, 100);
        loop {
            match tokio::time::timeout(WAIT, eventloop.poll()).await {
                Ok(Ok(rumqttc::v5::Event::Incoming(p5::Packet::ConnAck(_)))) => break,
                Ok(Ok(_)) => continue,
                Ok(Err(rumqttc::v5::ConnectionError::ConnectionRefused(code))) => {
                    return Err(format!("{code:?}"))
                }
                Ok(Err(e)) => return Err(format!("{e}")),
                Err(_) => return Err("timeout".into()),
            }
        }
        let (tx, incoming) = mpsc::unbounded_channel();
        let task = tokio::spawn(async move {
            loop {
                match eventloop.poll().await {
                    Ok(rumqttc::v5::Event::Incoming(packet)) => {
                        if tx.send(Ok(packet)).is_err() {
                            return;
                        }
                    }
                    Ok(_) => {}
                    Err(e) => {
                        let _ = tx.send(Err(format!("{e:?}")));
                        return;
                    }
                }
            }
        });
        Ok(V5 {
            client,
            incoming,
            task,
        })
    }

    pub async fn next<T>(
        &mut self,
        within: Duration,
        mut pick: impl FnMut(p5::Packet) -> Option<T>,
    ) -> Option<T> {
        let deadline = tokio::time::Instant::now() + within;
        loop {
            let packet = tokio::time::timeout_at(deadline, self.incoming.recv())
                .await
                .ok()??;
            if let Some(t) = pick(packet.ok()?) {
                return Some(t);
            }
        }
    }

    /// The error that ended the connection, e.g. `SubFail { reason: NotAuthorized }`.
    pub async fn error(&mut self, within: Duration) -> Option<String> {
        let deadline = tokio::time::Instant::now() + within;
        loop {
            let item = tokio::time::timeout_at(deadline, self.incoming.recv())
                .await
                .ok()??;
            if let Err(e) = item {
                return Some(e);
            }
        }
    }

    pub async fn next_publish(&mut self, within: Duration) -> Option<p5::Publish> {
        self.next(within, |p| match p {
            p5::Packet::Publish(p) => Some(p),
            _ => None,
        })
        .await
    }

    pub async fn subscribe(&mut self, filter: &str) -> Vec<p5::SubscribeReasonCode> {
        self.client
            .subscribe(filter, rumqttc::v5::mqttbytes::QoS::AtLeastOnce)
            .await
            .unwrap();
        self.next(WAIT, |p| match p {
            p5::Packet::SubAck(s) => Some(s.return_codes),
            _ => None,
        })
        .await
        .expect("SUBACK")
    }

    pub fn alive(&self) -> bool {
        !self.task.is_finished()
    }
}

impl Drop for V5 {
    fn drop(&mut self) {
        self.task.abort();
    }
}
