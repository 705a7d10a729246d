//! Helpers the registry's test files share.

use controller_service::registry::{Served, Via};
use controller_service::Registry;
use protocol::pb;

/// The registry's one entry point for a sample on `id`'s own key, as the service calls it
/// (a fixed time: nothing here depends on it): the command to publish, or why none.
pub trait Answer {
    fn answer(&mut self, id: &str, s: &pb::Sample) -> Result<pb::Command, Served>;
}

impl Answer for Registry {
    fn answer(&mut self, id: &str, s: &pb::Sample) -> Result<pb::Command, Served> {
        let mut c = pb::Command::default();
        match self.handle_sample(Via::key(id), s, 1, &mut c) {
            Served::Answered { .. } => Ok(c),
            other => Err(other),
        }
    }
}

/// The command of an answered sample; a test failure naming why there was none.
pub fn answered(o: Result<pb::Command, Served>) -> pb::Command {
    match o {
        Ok(c) => c,
        Err(other) => panic!("no reply: {other:?}"),
    }
}
