//! `fbbus bus-cert`: the plant's bus CA and one certificate per line, zenoh router or
//! zenoh application, for mutual TLS between lines on the zenoh bus
//! (docs/bus-security.md), without openssl.
//!
//! A certificate's common name (CN) is who it is on the bus: a line's CN is its
//! `[broker] line`, and every other line lists the CNs it accepts in `[bridge.peers]`. So
//! `issue` takes only names a line may have, and puts the name nowhere else but the CN.

use std::fs::{DirBuilder, OpenOptions};
use std::io::{ErrorKind, Write as _};
use std::os::unix::fs::{DirBuilderExt as _, MetadataExt as _, OpenOptionsExt as _};
use std::path::{Path, PathBuf};
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use anyhow::{bail, Context as _, Result};
use clap::{Args, Subcommand};
use rcgen::{
    BasicConstraints, BmpString, CertificateParams, DistinguishedName, DnType, DnValue,
    ExtendedKeyUsagePurpose, IsCa, KeyIdMethod, KeyPair, KeyUsagePurpose, SanType, UniversalString,
};
use tokio_rustls::rustls::pki_types::ServerName;
use x509_parser::certificate::X509Certificate;
use x509_parser::der_parser::asn1_rs::Tag;
use x509_parser::extensions::ParsedExtension;

/// The CA's files in its directory: `--out` of `ca`, `--ca` of `issue`.
const CA_CERT: &str = "bus-ca.crt";
const CA_KEY: &str = "bus-ca.key";

/// Private keys: the owner only. Certificates are public.
const KEY_MODE: u32 = 0o600;
const CERT_MODE: u32 = 0o644;
/// A directory the command creates holds a private key: the owner only.
const DIR_MODE: u32 = 0o700;

/// A new certificate is valid from an hour ago: a line whose clock is a little behind
/// accepts it at once.
const BACKDATE: Duration = Duration::from_secs(3600);
const DAY: Duration = Duration::from_secs(86_400);

#[derive(Subcommand)]
pub enum Action {
    /// Create the plant's bus CA: DIR/bus-ca.crt (copy it to every line and router as
    /// `[bridge.tls] root_ca`) and DIR/bus-ca.key (keep it offline).
    Ca(CaArgs),
    /// Issue the certificate of one line, zenoh router or zenoh application, signed by the
    /// bus CA: DIR/NAME.crt and DIR/NAME.key.
    Issue(IssueArgs),
}

#[derive(Args)]
pub struct CaArgs {
    /// Directory to write bus-ca.crt and bus-ca.key to (created, mode 0700, if missing).
    #[arg(long, value_name = "DIR")]
    out: PathBuf,
    /// The CA's common name.
    #[arg(long, default_value = "fbbus bus CA")]
    name: String,
    /// Validity in days.
    #[arg(long, default_value_t = 3650, value_parser = days())]
    days: u32,
    /// Replace existing files.
    #[arg(long)]
    force: bool,
}

#[derive(Args)]
pub struct IssueArgs {
    /// Directory of the CA (bus-ca.crt and bus-ca.key).
    #[arg(long, value_name = "DIR")]
    ca: PathBuf,
    /// The common name: the line's `[broker] line`, or the router or application name
    /// the lines list in `[bridge.peers]`.
    #[arg(long, value_parser = peer_name)]
    name: String,
    /// A DNS name or IP address the others connect to (repeat for each); zenoh checks it
    /// on connect. Default: localhost and 127.0.0.1.
    #[arg(long = "host", value_name = "HOST")]
    hosts: Vec<String>,
    /// Validity in days.
    #[arg(long, default_value_t = 825, value_parser = days())]
    days: u32,
    /// Directory to write NAME.crt and NAME.key to (created, mode 0700, if missing).
    #[arg(long, value_name = "DIR")]
    out: PathBuf,
    /// For a read-only zenoh application (`[bridge.peers] readers`): client
    /// authentication only, so the certificate cannot serve a TLS listener.
    #[arg(long)]
    reader: bool,
    /// Replace existing files.
    #[arg(long)]
    force: bool,
}

/// Up to a hundred years: the date types underneath end at the year 9999.
fn days() -> clap::builder::RangedI64ValueParser<u32> {
    clap::value_parser!(u32).range(1..=36_500)
}

fn peer_name(name: &str) -> Result<String, String> {
    if !fb_bridge::bus::keys::valid_line(name) {
        return Err("use 1 to 64 letters, digits, `-`, `_` or `.`".into());
    }
    if name == "bus-ca" {
        return Err("`bus-ca` names the CA's own files; choose another name".into());
    }
    Ok(name.to_owned())
}

pub fn run(action: Action) -> Result<()> {
    match action {
        Action::Ca(args) => ca(args),
        Action::Issue(args) => issue(args),
    }
}

fn ca(args: CaArgs) -> Result<()> {
    let cert_path = args.out.join(CA_CERT);
    let key_path = args.out.join(CA_KEY);
    refuse_existing(&[&cert_path, &key_path], args.force)?;
    if args.name.trim().is_empty() {
        bail!("the CA needs a name (--name)");
    }

    let mut params = CertificateParams::default();
    params.distinguished_name = DistinguishedName::new();
    params
        .distinguished_name
        .push(DnType::CommonName, args.name.as_str());
    // Path length 0: the CA signs the certificates of lines, routers and applications
    // directly, never another CA.
    params.is_ca = IsCa::Ca(BasicConstraints::Constrained(0));
    params.key_usages = vec![KeyUsagePurpose::KeyCertSign, KeyUsagePurpose::CrlSign];
    let not_after = set_validity(&mut params, args.days);
    let key = KeyPair::generate().context("cannot generate the CA key")?;
    let cert = params
        .self_signed(&key)
        .context("cannot create the CA certificate")?;

    write_pair(
        &args.out,
        (&cert_path, &cert),
        (&key_path, &key),
        args.force,
    )?;
    println!("  CN: {}", args.name);
    println!(
        "  expires: {}",
        humantime::format_rfc3339_seconds(not_after)
    );
    println!(
        "Copy {CA_CERT} to every line and router ([bridge.tls] root_ca). Keep {CA_KEY} \
         offline, not on a line host: whoever has it can join the bus."
    );
    Ok(())
}

fn issue(args: IssueArgs) -> Result<()> {
    let cert_path = args.out.join(format!("{}.crt", args.name));
    let key_path = args.out.join(format!("{}.key", args.name));
    refuse_existing(&[&cert_path, &key_path], args.force)?;
    let hosts = if args.hosts.is_empty() {
        vec!["localhost".to_owned(), "127.0.0.1".to_owned()]
    } else {
        args.hosts
    };
    let sans = hosts
        .iter()
        .map(|h| subject_alt_name(h))
        .collect::<Result<Vec<_>>>()?;

    let ca_cert_path = args.ca.join(CA_CERT);
    let ca_key_path = args.ca.join(CA_KEY);
    let ca_key = read_ca_key(&ca_key_path)?;
    let ca_pems = read(&ca_cert_path)?;
    let ca_ders = rustls_pemfile::certs(&mut ca_pems.as_slice())
        .collect::<Result<Vec<_>, _>>()
        .with_context(|| format!("{}: not a PEM certificate file", ca_cert_path.display()))?;
    // During a CA rotation the file may be a bundle: the CA is the certificate of this key.
    let ca = ca_ders
        .iter()
        .filter_map(|der| x509_parser::parse_x509_certificate(der).ok())
        .map(|(_, cert)| cert)
        .find(|cert| cert.public_key().subject_public_key.data == ca_key.public_key_raw())
        .with_context(|| {
            format!(
                "{}: no certificate for the key in {}; --ca must be the directory \
                 `fbbus bus-cert ca` wrote",
                ca_cert_path.display(),
                ca_key_path.display()
            )
        })?;
    if !ca.is_ca() {
        bail!("{}: not a CA certificate", ca_cert_path.display());
    }

    let mut params = CertificateParams::default();
    params.distinguished_name = DistinguishedName::new();
    params
        .distinguished_name
        .push(DnType::CommonName, args.name.as_str());
    params.subject_alt_names = sans;
    params.is_ca = IsCa::ExplicitNoCa;
    params.key_usages = vec![KeyUsagePurpose::DigitalSignature];
    // A line both listens and connects, and so does a router; an application only
    // connects, and without serverAuth no peer accepts it as a listener.
    params.extended_key_usages = if args.reader {
        vec![ExtendedKeyUsagePurpose::ClientAuth]
    } else {
        vec![
            ExtendedKeyUsagePurpose::ServerAuth,
            ExtendedKeyUsagePurpose::ClientAuth,
        ]
    };
    // A CA without a subject key identifier gets no authority key identifier in its
    // certificates: one that matches nothing would mislead a path builder.
    let key_id = subject_key_id(&ca);
    params.use_authority_key_identifier_extension = key_id.is_some();
    let issuer = issuer(&ca, key_id, &ca_key, &ca_cert_path)?;
    let not_after = set_validity(&mut params, args.days);
    // No serial number given: rcgen derives it from the new (random) public key, so each
    // certificate has its own.
    let key = KeyPair::generate().context("cannot generate the key")?;
    let cert = params
        .signed_by(&key, &issuer, &ca_key)
        .context("cannot sign the certificate")?;

    // The issuer name was rebuilt from the CA's subject (see `issuer`); a verifier
    // compares the two byte for byte, so a difference would give a certificate that
    // chains to nothing.
    let (_, leaf) = x509_parser::parse_x509_certificate(cert.der())
        .context("cannot read back the new certificate")?;
    if leaf.issuer().as_raw() != ca.subject().as_raw() {
        bail!(
            "{}: fbbus cannot reproduce this CA's subject name exactly; issue the \
             certificate with openssl instead (docs/bus-security.md)",
            ca_cert_path.display()
        );
    }

    write_pair(
        &args.out,
        (&cert_path, &cert),
        (&key_path, &key),
        args.force,
    )?;
    println!("  CN: {}", args.name);
    println!("  SANs: {}", hosts.join(", "));
    println!(
        "  usage: {}",
        if args.reader {
            "clientAuth (read-only application)"
        } else {
            "serverAuth, clientAuth"
        }
    );
    println!(
        "  expires: {}",
        humantime::format_rfc3339_seconds(not_after)
    );
    let ca_expiry =
        UNIX_EPOCH + Duration::from_secs(ca.validity().not_after.timestamp().max(0) as u64);
    if not_after > ca_expiry {
        println!(
            "  note: the CA expires first ({}); the certificate stops working then",
            humantime::format_rfc3339_seconds(ca_expiry)
        );
    }
    Ok(())
}

/// Valid from [`BACKDATE`] ago for `days` days; returns the expiry.
fn set_validity(params: &mut CertificateParams, days: u32) -> SystemTime {
    let now = SystemTime::now();
    let not_after = now + DAY * days;
    params.not_before = (now - BACKDATE).into();
    params.not_after = not_after.into();
    not_after
}

/// An IP address as an IP SAN, anything else as a DNS name: zenoh (rustls) verifies the
/// host of a `tls/` endpoint against one or the other, so accept what it would.
fn subject_alt_name(host: &str) -> Result<SanType> {
    let invalid = || format!("--host `{host}`: not a DNS name or an IP address");
    Ok(match ServerName::try_from(host).with_context(invalid)? {
        ServerName::IpAddress(ip) => SanType::IpAddress(ip.into()),
        ServerName::DnsName(name) => SanType::DnsName(name.as_ref().try_into()?),
        _ => bail!(invalid()),
    })
}

/// The CA as rcgen signs with. rcgen 0.13 signs only with an issuer certificate of its own
/// making, and takes two things from it: its subject name (the new certificate's issuer)
/// and its key identifier (the new certificate's authority key identifier). Both are
/// copied from the CA file; the copy is signed again with the CA key in memory and used
/// for nothing else. (rcgen's `CertificateParams::from_ca_cert_pem` does the same, but
/// needs x509-parser 0.16, a second copy of the ASN.1 crates next to the 0.18 zenoh uses.)
fn issuer(
    ca: &X509Certificate,
    key_id: Option<Vec<u8>>,
    key: &KeyPair,
    path: &Path,
) -> Result<rcgen::Certificate> {
    let cannot = |what: &str| {
        format!(
            "{}: fbbus cannot reproduce this CA's subject name ({what}); issue the \
             certificate with openssl instead (docs/bus-security.md)",
            path.display()
        )
    };
    let mut name = DistinguishedName::new();
    for rdn in ca.subject().iter() {
        let mut attributes = rdn.iter();
        let (Some(attribute), None) = (attributes.next(), attributes.next()) else {
            bail!(cannot("an entry with several attributes"));
        };
        let oid: Vec<u64> = attribute
            .attr_type()
            .iter()
            .with_context(|| cannot("an unusual attribute type"))?
            .collect();
        let value = attribute.attr_value();
        let text = || std::str::from_utf8(value.data).with_context(|| cannot("not UTF-8"));
        let bytes = value.data.to_vec();
        let value = match value.header.tag() {
            Tag::Utf8String => DnValue::Utf8String(text()?.to_owned()),
            Tag::PrintableString => DnValue::PrintableString(text()?.try_into()?),
            Tag::Ia5String => DnValue::Ia5String(text()?.try_into()?),
            Tag::T61String => DnValue::TeletexString(text()?.try_into()?),
            Tag::BmpString => DnValue::BmpString(BmpString::from_utf16be(bytes)?),
            Tag::UniversalString => DnValue::UniversalString(UniversalString::from_utf32be(bytes)?),
            _ => bail!(cannot("an unusual string type")),
        };
        name.push(DnType::from_oid(&oid), value);
    }

    let mut params = CertificateParams::default();
    params.distinguished_name = name;
    params.is_ca = IsCa::Ca(BasicConstraints::Unconstrained);
    // Without a key identifier of the CA's, none is written (see `issue`): any method does.
    params.key_identifier_method = key_id.map_or(KeyIdMethod::Sha256, KeyIdMethod::PreSpecified);
    params
        .self_signed(key)
        .with_context(|| format!("{}: cannot use this CA", path.display()))
}

fn subject_key_id(cert: &X509Certificate) -> Option<Vec<u8>> {
    cert.iter_extensions()
        .find_map(|e| match e.parsed_extension() {
            ParsedExtension::SubjectKeyIdentifier(id) => Some(id.0.to_vec()),
            _ => None,
        })
}

fn read(path: &Path) -> Result<Vec<u8>> {
    std::fs::read(path).with_context(|| {
        format!(
            "cannot read {}; --ca must be the directory `fbbus bus-cert ca` wrote",
            path.display()
        )
    })
}

/// The CA key, with a warning if others can read it.
fn read_ca_key(path: &Path) -> Result<KeyPair> {
    let pem = read(path)?;
    let mode = std::fs::metadata(path)?.mode() & 0o777;
    if mode & 0o077 != 0 {
        eprintln!(
            "fbbus: warning: {} is readable by others (mode {mode:o}); `chmod 600` it",
            path.display()
        );
    }
    let pem = String::from_utf8(pem)
        .with_context(|| format!("{}: not a PEM private key", path.display()))?;
    KeyPair::from_pem(&pem).with_context(|| {
        format!(
            "{}: not a usable private key (PKCS#8 PEM, `BEGIN PRIVATE KEY`)",
            path.display()
        )
    })
}

/// Checks every target before anything is generated or written, so that a refusal
/// leaves all files as they were.
fn refuse_existing(paths: &[&Path], force: bool) -> Result<()> {
    if force {
        return Ok(());
    }
    for path in paths {
        if path.symlink_metadata().is_ok() {
            bail!(
                "{} already exists; nothing written (--force replaces it)",
                path.display()
            );
        }
    }
    Ok(())
}

/// Writes the certificate and its key into `dir` (created if missing) and says so.
fn write_pair(
    dir: &Path,
    (cert_path, cert): (&Path, &rcgen::Certificate),
    (key_path, key): (&Path, &KeyPair),
    force: bool,
) -> Result<()> {
    DirBuilder::new()
        .recursive(true)
        .mode(DIR_MODE)
        .create(dir)
        .with_context(|| format!("cannot create the directory {}", dir.display()))?;
    write_new(cert_path, cert.pem().as_bytes(), CERT_MODE, force)?;
    write_new(key_path, key.serialize_pem().as_bytes(), KEY_MODE, force)?;
    println!("wrote {}", cert_path.display());
    println!("wrote {} (private key, mode 0600)", key_path.display());
    Ok(())
}

/// Writes a new file, created with `mode`: a key is never readable by others, not even
/// for a moment. With `force` an existing file is removed first, since opening it would
/// keep its old mode.
fn write_new(path: &Path, contents: &[u8], mode: u32, force: bool) -> Result<()> {
    if force {
        match std::fs::remove_file(path) {
            Err(e) if e.kind() != ErrorKind::NotFound => {
                return Err(e).with_context(|| format!("cannot replace {}", path.display()))
            }
            _ => {}
        }
    }
    let mut file = OpenOptions::new()
        .write(true)
        .create_new(true)
        .mode(mode)
        .open(path)
        .with_context(|| format!("cannot create {}", path.display()))?;
    file.write_all(contents)
        .and_then(|()| file.sync_all())
        .with_context(|| format!("cannot write {}", path.display()))
}
