//! The bus's PKI for tests (issue 22): a CA and one certificate per name, common name =
//! the name (a line, a router, a zenoh application), usable as TLS server and client, as
//! a plant's bus certificates are (docs/bus-security.md).
//!
//! [`bus`] is the one PKI of a test process (generated once): every line name the bus
//! tests use, for loopback. Tests on other addresses (network namespaces) make their own
//! with [`Pki::generate`] and the addresses as subject alternative names.

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use rcgen::{
    BasicConstraints, CertificateParams, DnType, ExtendedKeyUsagePurpose, IsCa, KeyPair,
    KeyUsagePurpose,
};

/// The names the bus tests give lines, routers and zenoh applications.
pub const LINES: [&str; 5] = ["line-a", "line-b", "line-c", "line-py", "line-r"];
pub const ROUTERS: [&str; 1] = ["line-r"];
pub const READERS: [&str; 1] = ["historian"];

/// A CA (PEM) and certificates and keys (PEM) by common name.
pub struct Pki {
    pub ca: String,
    certs: HashMap<String, (String, String)>,
}

/// Where a line's bus identity was written: the CA bundle, its certificate and key.
pub struct Files {
    pub ca: PathBuf,
    pub cert: PathBuf,
    pub key: PathBuf,
}

impl Pki {
    /// A CA named `ca_name` and a certificate for each of `names`, valid for the hosts
    /// and addresses `sans` (zenoh checks the name it connects to).
    pub fn generate(ca_name: &str, names: &[&str], sans: &[&str]) -> Pki {
        let ca_key = KeyPair::generate().unwrap();
        let mut ca_params = CertificateParams::new(Vec::<String>::new()).unwrap();
        ca_params.is_ca = IsCa::Ca(BasicConstraints::Unconstrained);
        ca_params
            .distinguished_name
            .push(DnType::CommonName, ca_name);
        ca_params.key_usages = vec![
            KeyUsagePurpose::KeyCertSign,
            KeyUsagePurpose::DigitalSignature,
        ];
        let ca = ca_params.self_signed(&ca_key).unwrap();
        let sans: Vec<String> = sans.iter().map(|s| s.to_string()).collect();
        let certs = names
            .iter()
            .map(|name| {
                let key = KeyPair::generate().unwrap();
                let mut params = CertificateParams::new(sans.clone()).unwrap();
                params.distinguished_name.push(DnType::CommonName, *name);
                params.use_authority_key_identifier_extension = true;
                params.key_usages = vec![KeyUsagePurpose::DigitalSignature];
                params.extended_key_usages = vec![
                    ExtendedKeyUsagePurpose::ServerAuth,
                    ExtendedKeyUsagePurpose::ClientAuth,
                ];
                let cert = params.signed_by(&key, &ca, &ca_key).unwrap();
                (name.to_string(), (cert.pem(), key.serialize_pem()))
            })
            .collect();
        Pki {
            ca: ca.pem(),
            certs,
        }
    }

    /// Writes the CA as `bus-ca.crt` and `name`'s certificate and key as `<name>.crt`,
    /// `<name>.key` into `dir`.
    pub fn write(&self, dir: &Path, name: &str) -> Files {
        let (cert, key) = self
            .certs
            .get(name)
            .unwrap_or_else(|| panic!("the test PKI has no certificate for {name}"));
        let files = Files {
            ca: dir.join("bus-ca.crt"),
            cert: dir.join(format!("{name}.crt")),
            key: dir.join(format!("{name}.key")),
        };
        std::fs::write(&files.ca, &self.ca).unwrap();
        std::fs::write(&files.cert, cert).unwrap();
        std::fs::write(&files.key, key).unwrap();
        files
    }

    /// `[bridge.tls]` (mutual, the default) for `name`, its files written into `dir`, and
    /// `[bridge.peers]` naming `lines`, `routers` and `readers`.
    pub fn bridge_tables(
        &self,
        dir: &Path,
        name: &str,
        (lines, routers, readers): (&[&str], &[&str], &[&str]),
    ) -> String {
        let files = self.write(dir, name);
        format!(
            "[bridge.tls]\nroot_ca = {:?}\ncert = {:?}\nkey = {:?}\n\n\
             [bridge.peers]\nlines = {lines:?}\nrouters = {routers:?}\nreaders = {readers:?}\n",
            files.ca.display().to_string(),
            files.cert.display().to_string(),
            files.key.display().to_string(),
        )
    }
}

/// The test process's bus PKI: every name of [`LINES`], [`ROUTERS`] and [`READERS`],
/// for `localhost` and `127.0.0.1`; generated once.
pub fn bus() -> &'static Pki {
    static PKI: OnceLock<Pki> = OnceLock::new();
    PKI.get_or_init(|| {
        // (The routers are lines too.)
        let names: Vec<&str> = LINES.iter().chain(&READERS).copied().collect();
        Pki::generate("fbbus bus test CA", &names, &["localhost", "127.0.0.1"])
    })
}

/// The `[bridge.tls]` and `[bridge.peers]` tables of line `name` on the test bus: every
/// test line, `line-r` also as a router, `historian` as a reader.
pub fn bus_tables(dir: &Path, name: &str) -> String {
    bus().bridge_tables(dir, name, (&LINES, &ROUTERS, &READERS))
}
