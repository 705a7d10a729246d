//! `mfc-deploy`: a fleet's security material and zenoh configs, generated from one
//! inventory file.
//!
//! A remote deployment needs a CA, a router certificate whose names match what clients
//! dial, a client certificate per service, device and operator (CN = its name, so the
//! router's access control can tell them apart), a zenoh config per host, and about five
//! access-control rules per device: zenoh has no per-subject substitution. Written by hand
//! that is error-prone in ways that fail silently (a missing wildcard rule stops control
//! with no error; a plant in peer mode is reachable around the router). So it is generated:
//! [`inventory`] reads the fleet, [`pki`] issues certificates, [`acl`] writes the rules,
//! [`configs`] the zenoh configs, and [`generate`] puts them in one bundle per host.

pub mod acl;
pub mod cli;
pub mod configs;
pub mod generate;
pub mod inventory;
pub mod pki;

pub use generate::{generate, CertAction, DeployReport};
pub use inventory::{IdentityKind, Inventory};

/// Why generation failed.
#[derive(Debug, thiserror::Error)]
pub enum DeployError {
    /// The inventory is unreadable or inconsistent.
    #[error("inventory: {0}")]
    Inventory(String),
    /// A certificate or key could not be made or read.
    #[error("certificates: {0}")]
    Pki(String),
    /// A file could not be read or written.
    #[error("{}: {reason}", path.display())]
    Io {
        /// The file.
        path: std::path::PathBuf,
        /// Why.
        reason: String,
    },
}
