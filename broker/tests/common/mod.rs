//! Test support of the broker's integration tests: the shared kit (`fbbus_testkit`: the
//! real `fbbus` binary on free loopback ports, the admin endpoint, bounded processes),
//! re-exported here, and what only these tests use: clients, emulators, the bus's lines,
//! network namespaces, the test PKI.
#![allow(dead_code)]

pub mod bus;
pub mod clients;
pub mod fb;
pub mod memory;
pub mod netns;
pub mod pki;
pub mod raw;

pub use fbbus_testkit::*;
