//! The operator's live console, in a browser.
//!
//! A small process joins the Zenoh network with the operator's identity (the same flags and
//! `--zenoh-config` file as `mfcctl`: in a secured deployment, the operator's client
//! config for the router) and serves one page on loopback. Devices appear and disappear as
//! their plants' liveliness tokens do; for each, live plots of outputs and references, of
//! commands and F estimates, the status and counters the service keeps, the envelope, and
//! forms that change gains (a partial change: only the named fields) or set a constant
//! reference. The page's script and style are bundled in the binary, so it works with no
//! internet access.
//!
//! * [`fleet`]: the view of the fleet: devices, bounded histories, checks of every message
//!   and of a change against the envelope. Pure, unit-tested with plain values.
//! * [`net`]: the Zenoh wiring that feeds it (liveliness, samples, commands, polls).
//! * [`http`]: the page and its JSON API, with the guard against cross-site requests.
//! * [`login`]: who may use it (users, roles, sessions, wrong-password locks). Pure.
//! * [`settings`]: the optional settings file.
//! * [`cli`]: the command line (the binary is a one-line `main`).
//!
//! It links only the core (`mfc`, `protocol`, `transport`): the queries it makes are
//! `transport::ops`, the same as `mfcctl`'s.

pub mod cli;
pub mod fleet;
pub mod http;
pub mod login;
pub mod net;
pub mod sessions;
pub mod settings;

/// Why the console cannot run.
#[derive(Debug, thiserror::Error)]
pub enum ConsoleError {
    /// The settings file.
    #[error(transparent)]
    Settings(#[from] settings::SettingsError),
    /// The Zenoh session or a declaration.
    #[error("zenoh: {0}")]
    Zenoh(String),
    /// The operators' key file.
    #[error("--key-file: {0}")]
    Key(#[from] protocol::auth::KeyError),
    /// A command-line value that cannot be used.
    #[error("{0}")]
    Usage(String),
    /// The HTTP listener.
    #[error("HTTP on {addr}: {source}")]
    Http {
        /// The address.
        addr: std::net::SocketAddr,
        /// The reason.
        source: std::io::Error,
    },
}
