//! TLS listeners: server certificates, mutual TLS with `client_ca`, plaintext refused,
//! unusable certificate files refused at start.

mod common;

use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use common::raw::{self, RawClient};
use common::{Broker, Options};
use rcgen::{
    BasicConstraints, CertificateParams, DnType, ExtendedKeyUsagePurpose, IsCa, KeyPair,
    KeyUsagePurpose,
};

/// Writes a CA (`ca.crt`), a server certificate for `localhost` and 127.0.0.1
/// (`server.crt`, `server.key`) and a client certificate (`client.crt`, `client.key`),
/// both signed by the CA, into `dir`.
fn write_pki(dir: &Path) {
    let ca_key = KeyPair::generate().unwrap();
    let mut ca_params = CertificateParams::new(Vec::<String>::new()).unwrap();
    ca_params.is_ca = IsCa::Ca(BasicConstraints::Unconstrained);
    ca_params
        .distinguished_name
        .push(DnType::CommonName, "fbbus test CA");
    ca_params.key_usages = vec![
        KeyUsagePurpose::KeyCertSign,
        KeyUsagePurpose::CrlSign,
        KeyUsagePurpose::DigitalSignature,
    ];
    let ca = ca_params.self_signed(&ca_key).unwrap();

    let leaf = |names: Vec<String>, cn: &str, purpose: ExtendedKeyUsagePurpose| {
        let key = KeyPair::generate().unwrap();
        let mut params = CertificateParams::new(names).unwrap();
        params.distinguished_name.push(DnType::CommonName, cn);
        params.use_authority_key_identifier_extension = true;
        params.key_usages = vec![KeyUsagePurpose::DigitalSignature];
        params.extended_key_usages = vec![purpose];
        let cert = params.signed_by(&key, &ca, &ca_key).unwrap();
        (cert.pem(), key.serialize_pem())
    };
    let (server_crt, server_key) = leaf(
        vec!["localhost".into(), "127.0.0.1".into()],
        "localhost",
        ExtendedKeyUsagePurpose::ServerAuth,
    );
    let (client_crt, client_key) = leaf(
        vec!["client.test".into()],
        "client",
        ExtendedKeyUsagePurpose::ClientAuth,
    );
    std::fs::write(dir.join("ca.crt"), ca.pem()).unwrap();
    std::fs::write(dir.join("server.crt"), server_crt).unwrap();
    std::fs::write(dir.join("server.key"), server_key).unwrap();
    std::fs::write(dir.join("client.crt"), client_crt).unwrap();
    std::fs::write(dir.join("client.key"), client_key).unwrap();
}

fn tls_broker(client_ca: bool) -> Broker {
    let mut listener_extra =
        "[listener.tls]\ncert = \"server.crt\"\nkey = \"server.key\"\n".to_owned();
    if client_ca {
        listener_extra.push_str("client_ca = \"ca.crt\"\n");
    }
    Broker::start_with(
        Options {
            listener_extra,
            ..Default::default()
        },
        write_pki,
    )
}

/// mosquitto_pub/_sub arguments for a TLS connection to the broker as `localhost`.
fn tls_args(broker: &Broker, client_cert: bool) -> Vec<String> {
    let path = |name: &str| broker.path(name).to_str().unwrap().to_owned();
    let mut args = vec![
        "-h".into(),
        "localhost".into(),
        "-p".into(),
        broker.port().to_string(),
        "--cafile".into(),
        path("ca.crt"),
    ];
    if client_cert {
        args.extend([
            "--cert".into(),
            path("client.crt"),
            "--key".into(),
            path("client.key"),
        ]);
    }
    args
}

/// A process killed and reaped when dropped, so a failed assertion leaves nothing behind.
struct ChildGuard(Option<Child>);

impl ChildGuard {
    /// Waits up to `limit` for the process to exit: (success, stdout).
    fn finish(&mut self, limit: Duration) -> (bool, String) {
        use std::io::Read;
        let mut child = self.0.take().unwrap();
        let status = common::wait_until(&mut child, limit);
        let mut out = String::new();
        if let Some(mut stdout) = child.stdout.take() {
            let _ = stdout.read_to_string(&mut out);
        }
        (status.is_some_and(|s| s.success()), out)
    }
}

impl Drop for ChildGuard {
    fn drop(&mut self) {
        if let Some(mut child) = self.0.take() {
            let _ = child.kill();
            let _ = child.wait();
        }
    }
}

/// Starts `mosquitto_sub -C 1 -W 5` on topic `t` and waits until it is connected and has
/// (very likely) subscribed.
fn start_sub(broker: &Broker, client_cert: bool) -> ChildGuard {
    let before = broker.metric("fbbus_connects_total");
    let sub = Command::new("mosquitto_sub")
        .args(tls_args(broker, client_cert))
        .args(["-i", "tls-sub", "-t", "t", "-C", "1", "-W", "5"])
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .expect("spawn mosquitto_sub");
    let mut guard = ChildGuard(Some(sub));
    if broker.wait_metric("fbbus_connects_total", before + 1.0) < before + 1.0 {
        let (_, out) = guard.finish(Duration::from_secs(1));
        panic!(
            "mosquitto_sub did not connect over TLS ({out}); log: {}",
            broker.log_text()
        );
    }
    // The gauge goes up just after the connect is counted.
    assert!(broker.wait_metric("fbbus_connections", 1.0) >= 1.0);
    guard
}

fn publish(broker: &Broker, client_cert: bool, id: &str, message: &str) -> (bool, String) {
    let (ok, _, err) = common::run(
        Command::new("mosquitto_pub")
            .args(tls_args(broker, client_cert))
            // Retained: the subscriber gets it even if its SUBSCRIBE is processed later.
            .args(["-i", id, "-t", "t", "-r", "-m", message]),
        Duration::from_secs(10),
    );
    (ok, err)
}

#[test]
fn tls_listener_accepts_tls_clients() {
    if !common::require("mosquitto_sub") {
        return;
    }
    let broker = tls_broker(false);
    let mut sub = start_sub(&broker, false);
    let (ok, err) = publish(&broker, false, "tls-pub", "hi");
    assert!(
        ok,
        "mosquitto_pub over TLS failed: {err}; log: {}",
        broker.log_text()
    );
    let (ok, out) = sub.finish(Duration::from_secs(8));
    assert!(
        ok,
        "mosquitto_sub over TLS got nothing; log: {}",
        broker.log_text()
    );
    assert_eq!(out.trim_end(), "hi");
    assert_eq!(
        broker.metric("fbbus_connects_refused_total{reason=\"tls_handshake\"}"),
        0.0,
        "log: {}",
        broker.log_text()
    );

    // Plaintext MQTT on the TLS port: no CONNACK.
    let mut plain = RawClient::connect(broker.port());
    plain
        .stream
        .set_read_timeout(Some(Duration::from_secs(5)))
        .unwrap();
    plain.send(&raw::Connect::default().bytes());
    match plain.read_packet() {
        None => {}
        Some((byte1, body)) => assert_ne!(
            byte1, 0x20,
            "a plaintext CONNECT got a CONNACK on a TLS listener ({body:?})"
        ),
    }
    assert!(
        broker.wait_metric(
            "fbbus_connects_refused_total{reason=\"tls_handshake\"}",
            1.0
        ) >= 1.0,
        "plaintext client not counted as a TLS handshake failure; log: {}",
        broker.log_text()
    );
    // mosquitto_sub and mosquitto_pub are gone, but the broker closes their sessions (and
    // lowers the gauge) after it shut their sockets down: waited for, bounded.
    let deadline = Instant::now() + Duration::from_secs(10);
    while broker.metric("fbbus_connections") != 0.0 && Instant::now() < deadline {
        std::thread::sleep(Duration::from_millis(50));
    }
    assert_eq!(broker.metric("fbbus_connections"), 0.0);
}

#[test]
fn client_certificates_are_required_when_client_ca_set() {
    if !common::require("mosquitto_sub") {
        return;
    }
    let broker = tls_broker(true);
    let mut sub = start_sub(&broker, true);

    let refused_before = broker.metric("fbbus_connects_refused_total{reason=\"tls_handshake\"}");
    let (ok, err) = publish(&broker, false, "no-cert", "without-cert");
    assert!(
        !ok,
        "mosquitto_pub without a client certificate succeeded; log: {}",
        broker.log_text()
    );
    assert!(
        !err.starts_with("timed out"),
        "mosquitto_pub without a certificate hung: {err}"
    );
    assert!(
        broker.wait_metric(
            "fbbus_connects_refused_total{reason=\"tls_handshake\"}",
            refused_before + 1.0
        ) >= refused_before + 1.0,
        "log: {}",
        broker.log_text()
    );

    let (ok, err) = publish(&broker, true, "with-cert", "with-cert");
    assert!(
        ok,
        "mosquitto_pub with a client certificate failed: {err}; log: {}",
        broker.log_text()
    );
    let (ok, out) = sub.finish(Duration::from_secs(8));
    assert!(ok, "mosquitto_sub got nothing; log: {}", broker.log_text());
    // The first (and only) message delivered is the authenticated one.
    assert_eq!(out.trim_end(), "with-cert");
}

#[test]
fn bad_tls_files_refuse_to_start() {
    let dir = tempfile::tempdir().unwrap();
    write_pki(dir.path());
    std::fs::write(
        dir.path().join("bad.crt"),
        "this is not a PEM certificate\n",
    )
    .unwrap();
    let mqtt = common::free_port();
    let admin = common::free_port();
    let config = dir.path().join("fbbus.toml");
    let write_config = |cert: &str| {
        std::fs::write(
            &config,
            format!(
                "[broker]\nline = \"test\"\n\
                 [[listener]]\nname = \"main\"\nbind = \"127.0.0.1:{mqtt}\"\n\
                 [listener.tls]\ncert = \"{cert}\"\nkey = \"server.key\"\n\
                 [admin]\nbind = \"127.0.0.1:{admin}\"\n"
            ),
        )
        .unwrap();
    };

    write_config("bad.crt");
    let started = Instant::now();
    let (ok, out, err) = common::run(
        Command::new(common::fbbus_bin())
            .args(["serve", "--config", config.to_str().unwrap()])
            .env_remove("RUST_LOG"),
        Duration::from_secs(10),
    );
    let took = started.elapsed();
    assert!(!ok, "fbbus started with a non-PEM certificate: {out}{err}");
    assert!(!err.starts_with("timed out"), "fbbus did not exit: {err}");
    assert!(
        took < Duration::from_secs(5),
        "fbbus took {took:?} to refuse"
    );
    assert!(
        format!("{out}{err}").contains("bad.crt"),
        "the error does not name the file: stdout {out:?} stderr {err:?}"
    );

    // The same config with a good certificate does start (the refusal was about the file).
    write_config("server.crt");
    let broker = Broker::spawn(
        dir,
        config.clone(),
        format!("127.0.0.1:{mqtt}").parse().unwrap(),
        format!("127.0.0.1:{admin}").parse().unwrap(),
    );
    assert!(
        broker.log_text().contains("listening"),
        "log: {}",
        broker.log_text()
    );
}
