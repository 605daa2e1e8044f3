//! Test support shared by every fbbus test crate (the broker's integration tests,
//! `loadtest`'s): the real `fbbus` binary started on free loopback ports with a generated
//! config, and the small things every such test needs around it.
//!
//! Why a crate: the broker's tests and the harness's tests each had their own broker
//! starter, port picker and binary lookup, and they drifted (one learned not to hand out
//! a port twice, the other did not). One place now, used as a dev-dependency; each test
//! crate keeps only what is its own (clients, emulators, the harness's report readers).
//!
//! - [`Broker`]: `fbbus serve` as a child process, ready when `/readyz` answers 200,
//!   killed when dropped; [`Options`] for what goes into its config.
//! - [`free_port`]: a loopback port, never the same twice in one test process.
//! - [`fbbus_bin`]: the binary under test, built once if missing.
//! - [`http_get`], [`metric_value`]: the admin endpoint without an HTTP client crate.
//! - [`run`], [`wait_until`], [`require`], [`npm_file`]: bounded child processes, and the
//!   peers `.ci/run` installs (missing: a failure in CI, a loud skip elsewhere).
//!
//! Network traffic goes only to 127.0.0.0/8.

mod binary;
mod broker;
mod http;
mod port;
mod process;

pub use binary::fbbus_bin;
pub use broker::{basic, metric_value, Broker, Options};
pub use http::{http_get, http_get_as, http_request};
pub use port::free_port;
pub use process::{add_user, have, npm_file, require, require_paho, run, wait_until};
