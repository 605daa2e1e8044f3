//! What can go wrong on the bus link, for the broker to report.

#[derive(Debug, thiserror::Error)]
pub enum LinkError {
    #[error("zenoh configuration `{key}`: {message}")]
    Config { key: String, message: String },
    #[error(
        "[bridge.tls] cert `{cert}` names `{name}`, but this bridge is `{line}` (the \
         [broker] line, or the router's name): a line is who its certificate says. Issue \
         one with common name `{line}` (`fbbus bus-cert issue --name {line}`, \
         docs/bus-security.md)"
    )]
    Identity {
        cert: String,
        name: String,
        line: String,
    },
    #[error("[bridge.tls] cert `{cert}`: {message}")]
    Certificate { cert: String, message: String },
    #[error("zenoh: {0}")]
    Zenoh(String),
}

pub(super) fn zerr(e: impl std::fmt::Display) -> LinkError {
    LinkError::Zenoh(e.to_string())
}
