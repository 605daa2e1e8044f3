//! Names the user gives the ports an import generates.
//!
//! An import names a FORTE FB's ports as FORTE does (`P_COUNT.REQ` carrying `SD_1`), which
//! is what the engineer sees in 4diac IDE but means nothing to a JSON consumer of
//! `fb/<device>/P_COUNT/REQ` (`{"SD_1": 3}`). [`PortNames`] holds the names the user
//! chooses instead (`P_COUNT.SD_1` → `COUNT`), and the importers name the ports with them
//! as they build the profile, so the interface, the WITH lists, the topic mappings and the
//! notes all use the new name (an import writes no `[will]` or `[periods]`, so there is
//! nothing else to follow).
//!
//! A name is checked when it is given (an IEC 61131-3 identifier, the rule of every port
//! name, [`is_identifier`]; one name per port) and once the import is done
//! ([`PortNames::finish`]): every name must have named a port, must not collide with
//! another port of its FB, and must not name a port whose name the wire fixes (a DINASORE
//! value's port is the key of its payload, a typed topic's port is the topic's last level).

use std::collections::{BTreeMap, BTreeSet};

use crate::interface::is_identifier;

/// A mistake in the names given, saying what to do.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum NameError {
    #[error(
        "{0:?} is not FB.PORT=NAME: write the port as the profile printed without names shows \
         it (FB.PORT), '=', then its new name"
    )]
    Syntax(String),
    #[error(
        "{fb}.{port}: the new name {name:?} is not an IEC 61131-3 identifier (a letter or _, \
         then letters, digits and _, at most 64 bytes): choose another"
    )]
    NotIdentifier {
        fb: String,
        port: String,
        name: String,
    },
    #[error("{fb}.{port} is given two names, {first:?} and {second:?}: keep one")]
    Twice {
        fb: String,
        port: String,
        first: String,
        second: String,
    },
    #[error(
        "{fb}.{port} names no port the import generates: use FB.PORT as the profile printed \
         without names shows it"
    )]
    NoSuchPort { fb: String, port: String },
    #[error("{fb}.{port} cannot be renamed: {why}")]
    Fixed {
        fb: String,
        port: String,
        why: String,
    },
    #[error(
        "{fb}.{port} renamed {name:?} collides with another port of FB {fb} named {name} (in \
         profile {device}): port names are unique within an FB, choose another"
    )]
    Collides {
        device: String,
        fb: String,
        port: String,
        name: String,
    },
}

/// The names chosen for generated ports: `(FB, port)` → new name, the FB and port as the
/// import names them without names. An FB name of several profiles (two client ids with
/// an instance of the same name) names the port in each.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct PortNames {
    names: BTreeMap<(String, String), String>,
    used: BTreeSet<(String, String)>,
    errors: Vec<NameError>,
}

impl PortNames {
    pub fn new() -> PortNames {
        PortNames::default()
    }

    pub fn is_empty(&self) -> bool {
        self.names.is_empty()
    }

    /// Names port `fb_port` (`FB.PORT`) `name`.
    pub fn add(&mut self, fb_port: &str, name: &str) -> Result<(), NameError> {
        let (fb, port) = fb_port
            .trim()
            .split_once('.')
            .filter(|(fb, port)| !fb.is_empty() && !port.is_empty())
            .ok_or_else(|| NameError::Syntax(format!("{fb_port}={name}")))?;
        let (fb, port, name) = (fb.to_owned(), port.to_owned(), name.trim().to_owned());
        if !is_identifier(&name) {
            return Err(NameError::NotIdentifier { fb, port, name });
        }
        match self.names.get(&(fb.clone(), port.clone())) {
            Some(first) if *first != name => Err(NameError::Twice {
                first: first.clone(),
                fb,
                port,
                second: name,
            }),
            _ => {
                self.names.insert((fb, port), name);
                Ok(())
            }
        }
    }

    /// Names a port from `FB.PORT=NAME` (the command line's `--name`).
    pub fn add_arg(&mut self, arg: &str) -> Result<(), NameError> {
        let (fb_port, name) = arg
            .split_once('=')
            .ok_or_else(|| NameError::Syntax(arg.to_owned()))?;
        self.add(fb_port, name)
    }

    /// The name of the port `port` an import generates for FB `fb`: the user's, or
    /// `port`.
    pub(crate) fn name(&mut self, fb: &str, port: &str) -> String {
        let key = (fb.to_owned(), port.to_owned());
        match self.names.get(&key) {
            Some(name) => {
                let name = name.clone();
                self.used.insert(key);
                name
            }
            None => port.to_owned(),
        }
    }

    /// A port whose name the wire fixes: a name given for it is an error saying `why`.
    pub(crate) fn fixed(&mut self, fb: &str, port: &str, why: &str) {
        let key = (fb.to_owned(), port.to_owned());
        if self.names.contains_key(&key) && self.used.insert(key) {
            self.errors.push(NameError::Fixed {
                fb: fb.to_owned(),
                port: port.to_owned(),
                why: why.to_owned(),
            });
        }
    }

    /// Checks the names of one FB's ports once named (`(generated, name)`): a name that
    /// is another port's is an error.
    pub(crate) fn check_fb(&mut self, device: &str, fb: &str, ports: &[(String, String)]) {
        let mut seen = BTreeSet::new();
        let mut taken = BTreeSet::new();
        for (_, name) in ports {
            if !seen.insert(name) {
                taken.insert(name);
            }
        }
        for (port, name) in ports {
            let renamed = self.names.contains_key(&(fb.to_owned(), port.clone()));
            if renamed && taken.contains(name) {
                self.errors.push(NameError::Collides {
                    device: device.to_owned(),
                    fb: fb.to_owned(),
                    port: port.clone(),
                    name: name.clone(),
                });
            }
        }
    }

    /// Every mistake found once the imports that use these names are done: names of no
    /// port, names that collide, names of ports the wire names.
    pub fn finish(&self) -> Result<(), Vec<NameError>> {
        let mut errors = self.errors.clone();
        for (fb, port) in self.names.keys() {
            if !self.used.contains(&(fb.clone(), port.clone())) {
                errors.push(NameError::NoSuchPort {
                    fb: fb.clone(),
                    port: port.clone(),
                });
            }
        }
        match errors.is_empty() {
            true => Ok(()),
            false => Err(errors),
        }
    }
}
