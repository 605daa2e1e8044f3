//! `fbbus bus-cert`: the real binary writes a CA and certificates into a temporary
//! directory; the tests read them back with x509-parser (names, usages, signature, file
//! modes, refusals) and use them for mutual TLS with rustls, as zenoh does between lines.
#![cfg(feature = "bridge")]

use std::os::unix::fs::PermissionsExt as _;
use std::path::Path;
use std::process::{Command, Output};
use std::sync::Arc;
use std::time::Duration;

use tokio::net::{TcpListener, TcpStream};
use tokio_rustls::rustls::pki_types::{CertificateDer, PrivateKeyDer, ServerName};
use tokio_rustls::rustls::server::WebPkiClientVerifier;
use tokio_rustls::rustls::{self, ClientConfig, RootCertStore, ServerConfig};
use tokio_rustls::{TlsAcceptor, TlsConnector};
use x509_parser::certificate::X509Certificate;
use x509_parser::extensions::{GeneralName, ParsedExtension};

fn fbbus(dir: &Path, args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_fbbus"))
        .current_dir(dir)
        .arg("bus-cert")
        .args(args)
        .output()
        .expect("run fbbus")
}

/// Runs `fbbus bus-cert ARGS` in `dir`, asserts success and returns its standard output.
fn ok(dir: &Path, args: &[&str]) -> String {
    let out = fbbus(dir, args);
    let stdout = String::from_utf8_lossy(&out.stdout).into_owned();
    assert!(
        out.status.success(),
        "fbbus bus-cert {args:?} failed: {}{stdout}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(!stdout.contains("PRIVATE KEY"), "key material printed");
    stdout
}

/// Runs `fbbus bus-cert ARGS` in `dir`, asserts failure and returns its standard error.
fn refused(dir: &Path, args: &[&str]) -> String {
    let out = fbbus(dir, args);
    assert!(!out.status.success(), "fbbus bus-cert {args:?} succeeded");
    String::from_utf8_lossy(&out.stderr).into_owned()
}

/// A CA in `dir/ca` and `names` issued into `dir/tls` with `extra` arguments each.
fn pki(dir: &Path, names: &[(&str, &[&str])]) {
    ok(dir, &["ca", "--out", "ca"]);
    for (name, extra) in names {
        let mut args = vec!["issue", "--ca", "ca", "--name", name, "--out", "tls"];
        args.extend_from_slice(extra);
        ok(dir, &args);
    }
}

/// The certificates of a PEM file, DER-encoded.
fn certs(path: &Path) -> Vec<CertificateDer<'static>> {
    let pem = std::fs::read(path).unwrap();
    rustls_pemfile::certs(&mut pem.as_slice())
        .collect::<Result<_, _>>()
        .unwrap()
}

fn key(path: &Path) -> PrivateKeyDer<'static> {
    let pem = std::fs::read(path).unwrap();
    rustls_pemfile::private_key(&mut pem.as_slice())
        .unwrap()
        .unwrap()
}

fn parse<'a>(der: &'a [u8]) -> X509Certificate<'a> {
    x509_parser::parse_x509_certificate(der).unwrap().1
}

fn common_name(cert: &X509Certificate) -> String {
    let cn = cert.subject().iter_common_name().next().expect("a CN");
    cn.as_str().unwrap().to_owned()
}

fn mode(path: &Path) -> u32 {
    std::fs::metadata(path).unwrap().permissions().mode() & 0o777
}

/// (server auth, client auth) of the extended key usage.
fn eku(cert: &X509Certificate) -> (bool, bool) {
    let eku = cert.extended_key_usage().unwrap().expect("an EKU").value;
    (eku.server_auth, eku.client_auth)
}

fn sans(cert: &X509Certificate) -> Vec<String> {
    let san = cert
        .subject_alternative_name()
        .unwrap()
        .expect("a SAN extension");
    san.value
        .general_names
        .iter()
        .map(|name| match name {
            GeneralName::DNSName(dns) => format!("DNS:{dns}"),
            GeneralName::IPAddress(ip) => {
                let ip: [u8; 4] = (*ip).try_into().expect("an IPv4 address");
                format!("IP:{}", std::net::Ipv4Addr::from(ip))
            }
            other => panic!("unexpected SAN {other:?}"),
        })
        .collect()
}

fn key_id(cert: &X509Certificate, authority: bool) -> Vec<u8> {
    cert.iter_extensions()
        .find_map(|e| match e.parsed_extension() {
            ParsedExtension::SubjectKeyIdentifier(id) if !authority => Some(id.0.to_vec()),
            ParsedExtension::AuthorityKeyIdentifier(aki) if authority => {
                Some(aki.key_identifier.as_ref()?.0.to_vec())
            }
            _ => None,
        })
        .expect("a key identifier")
}

#[test]
fn line_certificate_names_usages_and_chain() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    ok(d, &["ca", "--out", "ca"]);
    let printed = ok(
        d,
        &[
            "issue",
            "--ca",
            "ca",
            "--name",
            "line-a",
            "--host",
            "127.0.0.1",
            "--host",
            "line-a.plant",
            "--out",
            "tls",
        ],
    );
    assert!(printed.contains("CN: line-a"), "{printed}");
    assert!(printed.contains("127.0.0.1, line-a.plant"), "{printed}");
    assert!(printed.contains("expires: "), "{printed}");

    let ca_der = certs(&d.join("ca/bus-ca.crt")).remove(0);
    let ca = parse(&ca_der);
    assert!(ca.is_ca());
    assert_eq!(common_name(&ca), "fbbus bus CA");

    let leaf_ders = certs(&d.join("tls/line-a.crt"));
    assert_eq!(leaf_ders.len(), 1, "the leaf only");
    let leaf = parse(&leaf_ders[0]);
    assert_eq!(common_name(&leaf), "line-a");
    assert_eq!(sans(&leaf), ["IP:127.0.0.1", "DNS:line-a.plant"]);
    assert_eq!(eku(&leaf), (true, true));
    let usage = leaf.key_usage().unwrap().expect("a key usage").value;
    assert!(usage.digital_signature() && !usage.key_cert_sign());
    assert!(!leaf.is_ca());
    assert!(leaf.validity().time_to_expiration().unwrap() > Duration::from_secs(824 * 86_400));

    // Chains to the CA: issued by its name, under its key identifier, signed by its key.
    assert_eq!(leaf.issuer().as_raw(), ca.subject().as_raw());
    assert_eq!(key_id(&leaf, true), key_id(&ca, false));
    leaf.verify_signature(Some(ca.public_key()))
        .expect("signed by the CA");

    assert_eq!(mode(&d.join("ca/bus-ca.key")), 0o600);
    assert_eq!(mode(&d.join("tls/line-a.key")), 0o600);
    assert_eq!(mode(&d.join("tls/line-a.crt")), 0o644);
}

#[test]
fn default_hosts_and_reader() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    pki(d, &[("line-b", &[]), ("historian", &["--reader"])]);

    let der = certs(&d.join("tls/line-b.crt")).remove(0);
    assert_eq!(sans(&parse(&der)), ["DNS:localhost", "IP:127.0.0.1"]);

    let der = certs(&d.join("tls/historian.crt")).remove(0);
    let reader = parse(&der);
    assert_eq!(common_name(&reader), "historian");
    assert_eq!(eku(&reader), (false, true), "client authentication only");
}

#[test]
fn refuses_to_overwrite_without_force() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    pki(d, &[("line-a", &[])]);
    let crt = d.join("tls/line-a.crt");
    let key = d.join("tls/line-a.key");
    let (crt_before, key_before) = (std::fs::read(&crt).unwrap(), std::fs::read(&key).unwrap());

    let issue = ["issue", "--ca", "ca", "--name", "line-a", "--out", "tls"];
    let error = refused(d, &issue);
    assert!(
        error.contains("already exists") && error.contains("--force"),
        "{error}"
    );
    assert_eq!(std::fs::read(&crt).unwrap(), crt_before);
    assert_eq!(std::fs::read(&key).unwrap(), key_before);
    let ca_key = std::fs::read(d.join("ca/bus-ca.key")).unwrap();
    let error = refused(d, &["ca", "--out", "ca"]);
    assert!(error.contains("--force"), "{error}");
    assert_eq!(std::fs::read(d.join("ca/bus-ca.key")).unwrap(), ca_key);

    // --force replaces both files, and the key is created anew with mode 0600 even where
    // the old file had looser permissions.
    std::fs::set_permissions(&key, std::fs::Permissions::from_mode(0o644)).unwrap();
    ok(d, &[&issue[..], &["--force"]].concat());
    assert_ne!(std::fs::read(&crt).unwrap(), crt_before);
    assert_ne!(std::fs::read(&key).unwrap(), key_before);
    assert_eq!(mode(&key), 0o600);
}

#[test]
fn refuses_bad_names_and_hosts() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    pki(d, &[]);
    let error = refused(
        d,
        &["issue", "--ca", "ca", "--name", "line/a", "--out", "tls"],
    );
    assert!(error.contains("letters, digits"), "{error}");
    let error = refused(
        d,
        &[
            "issue", "--ca", "ca", "--name", "line-a", "--host", "a b", "--out", "tls",
        ],
    );
    assert!(error.contains("not a DNS name or an IP address"), "{error}");
    let error = refused(
        d,
        &[
            "issue", "--ca", "nowhere", "--name", "line-a", "--out", "tls",
        ],
    );
    assert!(error.contains("nowhere/bus-ca.key"), "{error}");
    assert!(!d.join("tls").exists(), "nothing written");
}

/// During a CA rotation bus-ca.crt may hold the old and the new CA: `issue` signs with the
/// one that belongs to bus-ca.key.
#[test]
fn issues_from_a_ca_bundle() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    ok(d, &["ca", "--out", "old", "--name", "old CA"]);
    ok(d, &["ca", "--out", "ca", "--name", "new CA"]);
    let mut bundle = std::fs::read(d.join("old/bus-ca.crt")).unwrap();
    bundle.extend(std::fs::read(d.join("ca/bus-ca.crt")).unwrap());
    std::fs::write(d.join("ca/bus-ca.crt"), bundle).unwrap();
    ok(
        d,
        &["issue", "--ca", "ca", "--name", "line-a", "--out", "tls"],
    );

    let cas = certs(&d.join("ca/bus-ca.crt"));
    let new_ca = parse(&cas[1]);
    let der = certs(&d.join("tls/line-a.crt")).remove(0);
    let leaf = parse(&der);
    assert_eq!(leaf.issuer().as_raw(), new_ca.subject().as_raw());
    leaf.verify_signature(Some(new_ca.public_key())).unwrap();
}

/// A CA made by another tool, with a subject of several attributes and string types:
/// `issue` writes it as the issuer byte for byte, so the certificate chains.
#[test]
fn issues_from_a_ca_made_elsewhere() {
    use rcgen::{BasicConstraints, CertificateParams, DnType, DnValue, IsCa, KeyPair};
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let key = KeyPair::generate().unwrap();
    let mut params = CertificateParams::new(Vec::<String>::new()).unwrap();
    let printable = |s: &str| DnValue::PrintableString(s.try_into().unwrap());
    params.distinguished_name.remove(DnType::CommonName);
    params
        .distinguished_name
        .push(DnType::CountryName, printable("DE"));
    params
        .distinguished_name
        .push(DnType::OrganizationName, "Werk Süd");
    params
        .distinguished_name
        .push(DnType::CommonName, printable("Plant bus CA"));
    params.is_ca = IsCa::Ca(BasicConstraints::Unconstrained);
    let ca = params.self_signed(&key).unwrap();
    std::fs::create_dir(d.join("ca")).unwrap();
    std::fs::write(d.join("ca/bus-ca.crt"), ca.pem()).unwrap();
    std::fs::write(d.join("ca/bus-ca.key"), key.serialize_pem()).unwrap();
    std::fs::set_permissions(
        d.join("ca/bus-ca.key"),
        std::fs::Permissions::from_mode(0o600),
    )
    .unwrap();
    ok(
        d,
        &["issue", "--ca", "ca", "--name", "line-a", "--out", "tls"],
    );

    let ca = parse(ca.der());
    let der = certs(&d.join("tls/line-a.crt")).remove(0);
    let leaf = parse(&der);
    assert_eq!(leaf.issuer().as_raw(), ca.subject().as_raw());
    assert_eq!(key_id(&leaf, true), key_id(&ca, false));
    leaf.verify_signature(Some(ca.public_key())).unwrap();
}

// ---------------------------------------------------------------------------------------
// Mutual TLS with the issued certificates, as zenoh's TLS links use them.

fn provider() -> Arc<rustls::crypto::CryptoProvider> {
    Arc::new(rustls::crypto::ring::default_provider())
}

fn roots(ca: &Path) -> Arc<RootCertStore> {
    let mut roots = RootCertStore::empty();
    for cert in certs(ca) {
        roots.add(cert).unwrap();
    }
    Arc::new(roots)
}

/// A server that requires a client certificate from `ca`, presenting `name`'s.
fn acceptor(ca: &Path, dir: &Path, name: &str) -> TlsAcceptor {
    let verifier = WebPkiClientVerifier::builder_with_provider(roots(ca), provider())
        .build()
        .unwrap();
    let config = ServerConfig::builder_with_provider(provider())
        .with_safe_default_protocol_versions()
        .unwrap()
        .with_client_cert_verifier(verifier)
        .with_single_cert(
            certs(&dir.join(format!("{name}.crt"))),
            key(&dir.join(format!("{name}.key"))),
        )
        .unwrap();
    TlsAcceptor::from(Arc::new(config))
}

/// A client that trusts `ca` and presents `name`'s certificate.
fn connector(ca: &Path, dir: &Path, name: &str) -> TlsConnector {
    let config = ClientConfig::builder_with_provider(provider())
        .with_safe_default_protocol_versions()
        .unwrap()
        .with_root_certificates(roots(ca))
        .with_client_auth_cert(
            certs(&dir.join(format!("{name}.crt"))),
            key(&dir.join(format!("{name}.key"))),
        )
        .unwrap();
    TlsConnector::from(Arc::new(config))
}

/// What each side of a handshake saw: the server, the CN of the client's certificate.
struct Handshake {
    client: Result<(), String>,
    server: Result<String, String>,
}

/// One handshake on loopback, client to server by IP address (as a `tls/10.0.2.1:7447`
/// endpoint does).
async fn handshake(acceptor: TlsAcceptor, connector: TlsConnector) -> Handshake {
    use tokio::io::{AsyncReadExt as _, AsyncWriteExt as _};
    let listener = TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = listener.local_addr().unwrap();
    let server = tokio::spawn(async move {
        let (tcp, _) = listener.accept().await.unwrap();
        let mut tls = acceptor.accept(tcp).await.map_err(|e| e.to_string())?;
        let der = tls.get_ref().1.peer_certificates().unwrap()[0].clone();
        tls.write_all(b"ok").await.map_err(|e| e.to_string())?;
        tls.shutdown().await.map_err(|e| e.to_string())?;
        Ok(common_name(&parse(&der)))
    });
    let client = async {
        let tcp = TcpStream::connect(addr).await.unwrap();
        let name = ServerName::IpAddress(addr.ip().into());
        let mut tls = connector
            .connect(name, tcp)
            .await
            .map_err(|e| e.to_string())?;
        // With TLS 1.3 the server checks the client's certificate after the client has
        // finished: only the server's first bytes show that it was accepted.
        let mut buf = [0; 2];
        tls.read_exact(&mut buf).await.map_err(|e| e.to_string())?;
        Ok(())
    };
    let limit = Duration::from_secs(10);
    let client = tokio::time::timeout(limit, client)
        .await
        .expect("client hangs");
    let server = tokio::time::timeout(limit, server)
        .await
        .expect("server hangs");
    Handshake {
        client,
        server: server.unwrap(),
    }
}

/// Asserts the handshake succeeded and returns the client's CN as the server saw it.
fn accepted(handshake: Handshake) -> String {
    handshake.client.expect("client side");
    handshake.server.expect("server side")
}

#[tokio::test]
async fn certificates_work_for_mutual_tls() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    pki(
        d,
        &[
            ("line-a", &["--host", "127.0.0.1"]),
            ("line-b", &["--host", "127.0.0.1"]),
            ("historian", &["--reader"]),
        ],
    );
    let (ca, tls) = (d.join("ca/bus-ca.crt"), d.join("tls"));

    let seen = handshake(
        acceptor(&ca, &tls, "line-a"),
        connector(&ca, &tls, "line-b"),
    )
    .await;
    assert_eq!(accepted(seen), "line-b");
    // Each line both listens and connects.
    let seen = handshake(
        acceptor(&ca, &tls, "line-b"),
        connector(&ca, &tls, "line-a"),
    )
    .await;
    assert_eq!(accepted(seen), "line-a");
    let seen = handshake(
        acceptor(&ca, &tls, "line-a"),
        connector(&ca, &tls, "historian"),
    )
    .await;
    assert_eq!(accepted(seen), "historian");
}

#[tokio::test]
async fn certificates_of_another_ca_and_readers_as_servers_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    pki(
        d,
        &[
            ("line-a", &["--host", "127.0.0.1"]),
            ("historian", &["--reader"]),
        ],
    );
    ok(d, &["ca", "--out", "other-ca", "--name", "another plant"]);
    ok(
        d,
        &[
            "issue",
            "--ca",
            "other-ca",
            "--name",
            "line-b",
            "--host",
            "127.0.0.1",
            "--out",
            "other",
        ],
    );
    let (ca, tls) = (d.join("ca/bus-ca.crt"), d.join("tls"));
    let (other_ca, other) = (d.join("other-ca/bus-ca.crt"), d.join("other"));

    // A client with a certificate of another CA (it trusts the plant's CA, which is
    // public): the server refuses it.
    let seen = handshake(
        acceptor(&ca, &tls, "line-a"),
        connector(&ca, &other, "line-b"),
    )
    .await;
    let error = seen.server.expect_err("server refuses the client");
    assert!(error.contains("UnknownIssuer"), "{error}");
    assert!(seen.client.is_err());
    // A server with a certificate of another CA: the client refuses it.
    let seen = handshake(
        acceptor(&other_ca, &other, "line-b"),
        connector(&ca, &tls, "line-a"),
    )
    .await;
    let error = seen.client.expect_err("client refuses the server");
    assert!(error.contains("UnknownIssuer"), "{error}");
    // A reader's certificate (client authentication only) cannot serve.
    let seen = handshake(
        acceptor(&ca, &tls, "historian"),
        connector(&ca, &tls, "line-a"),
    )
    .await;
    let error = seen
        .client
        .expect_err("client refuses the reader as a server");
    assert!(error.contains("extended key usage"), "{error}");
}

/// The CA rotation of docs/bus-security.md: with the old and the new CA in one `root_ca`,
/// a line with a certificate of either CA links to a line with one of the other.
#[tokio::test]
async fn a_ca_bundle_accepts_old_and_new_certificates() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    ok(d, &["ca", "--out", "old-ca", "--name", "old CA"]);
    ok(d, &["ca", "--out", "new-ca", "--name", "new CA"]);
    ok(
        d,
        &[
            "issue", "--ca", "old-ca", "--name", "line-a", "--out", "old",
        ],
    );
    ok(
        d,
        &[
            "issue", "--ca", "new-ca", "--name", "line-b", "--out", "new",
        ],
    );
    let mut bundle = std::fs::read(d.join("old-ca/bus-ca.crt")).unwrap();
    bundle.extend(std::fs::read(d.join("new-ca/bus-ca.crt")).unwrap());
    let root_ca = d.join("bundle.crt");
    std::fs::write(&root_ca, bundle).unwrap();
    let (old, new) = (d.join("old"), d.join("new"));

    let seen = handshake(
        acceptor(&root_ca, &old, "line-a"),
        connector(&root_ca, &new, "line-b"),
    )
    .await;
    assert_eq!(accepted(seen), "line-b");
    let seen = handshake(
        acceptor(&root_ca, &new, "line-b"),
        connector(&root_ca, &old, "line-a"),
    )
    .await;
    assert_eq!(accepted(seen), "line-a");
}
