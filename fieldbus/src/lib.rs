//! Plants behind industrial protocols, as [`plant::Plant`]s: what lets a PLC's loop, a
//! drive or a gateway be controlled with no driver of one's own.
//!
//! * [`modbus::ModbusBridge`]: a Modbus TCP client through the register map of the plant
//!   file (`[plant.modbus]`, [`plant::modbus`]);
//! * [`opcua::OpcUaBridge`]: an OPC UA client through the node ids of the plant file
//!   (`[plant.opcua]`, [`plant::opcua`]);
//! * [`open`]: the plant a scenario names, whichever its kind: the AERO simulator and
//!   driver processes through [`plant::open`], the bridges here;
//! * [`probe`]: what a server holds, for a user writing the map.
//!
//! Why a crate of its own: the `plant` crate links no network runtime (the offline bench
//! needs none), and a Modbus client brings tokio. The map (what the plant file says, its
//! codec and its request plan) lives in `plant`, where the loader checks it; this crate is
//! only the wire.

pub mod modbus;
pub mod opcua;
pub mod probe;
pub mod reconnect;

use plant::scenario::PlantSource;
use plant::{Plant, PlantError};

/// Open the plant `source` names and check its channel count against `channels`:
/// [`plant::open`] for a simulator or a driver, the bridge for a server.
pub fn open(
    source: &PlantSource,
    seed: u64,
    channels: usize,
) -> Result<Box<dyn Plant>, PlantError> {
    match source {
        PlantSource::Modbus(m) => {
            let bridge = modbus::ModbusBridge::connect(m)?;
            if bridge.channels() != channels {
                return Err(PlantError::Channels {
                    plant: bridge.channels(),
                    scenario: channels,
                });
            }
            Ok(Box::new(bridge))
        }
        PlantSource::OpcUa(o) => {
            let bridge = opcua::OpcUaBridge::connect(o)?;
            if bridge.channels() != channels {
                return Err(PlantError::Channels {
                    plant: bridge.channels(),
                    scenario: channels,
                });
            }
            Ok(Box::new(bridge))
        }
        _ => plant::open(source, seed, channels),
    }
}

/// Run `f` where a client's runtime may block: here, or, on an async worker (where tokio
/// forbids blocking on a runtime, as a bridge dropped in async code would), on a scoped
/// thread of its own.
pub(crate) fn off_async<T: Send>(f: impl FnOnce() -> T + Send) -> T {
    if tokio::runtime::Handle::try_current().is_ok() {
        std::thread::scope(|s| {
            s.spawn(f)
                .join()
                .unwrap_or_else(|p| std::panic::resume_unwind(p))
        })
    } else {
        f()
    }
}
