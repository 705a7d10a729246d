//! The agent's rules on the wire: how a decoded [`pb::Command`] becomes the
//! [`IncomingCommand`] the [`Supervisor`](crate::safety::Supervisor) judges, and how the
//! supervisor's [`LoopMode`] is reported in a [`pb::Sample`]'s flags.
//!
//! The rules themselves ([`crate::safety`]) know nothing of the protocol; this mapping is
//! the one place that does. It is public so that a loop run elsewhere, like the bench's
//! lockstep network simulator (`mfc_lab::netsim`), judges commands and flags samples
//! exactly as the agent does, rather than with a copy that could drift.

use protocol::pb;

use crate::lease::Credentials;
use crate::safety::{CommandBody, IncomingCommand, LoopMode};

impl<'a> IncomingCommand<'a> {
    /// A decoded command as the supervisor judges it: a control, a warming-up answer, a
    /// refusal (with its reason), or a mode this agent does not know (STALE included),
    /// which the supervisor counts as malformed. The device id is the caller's to check.
    pub fn from_wire(cmd: &'a pb::Command) -> Self {
        let body = match pb::Mode::try_from(cmd.mode) {
            Ok(pb::Mode::Control) => CommandBody::Control(&cmd.v),
            Ok(pb::Mode::WarmingUp) => CommandBody::WarmingUp,
            Ok(pb::Mode::Rejected) => CommandBody::Rejected(&cmd.error),
            _ => CommandBody::Unknown,
        };
        IncomingCommand {
            seq: cmd.seq,
            body,
            horizon: &cmd.horizon,
            lease: Credentials {
                from: &cmd.controller_id,
                instance: cmd.lease_instance,
                epoch: cmd.lease_epoch,
                claim: cmd.claim,
                release: cmd.release,
                run_id: cmd.run_id,
            },
        }
    }
}

/// The sample flags that report `mode` (none while remote).
pub fn sample_flags(mode: LoopMode) -> u32 {
    match mode {
        LoopMode::Remote => 0,
        LoopMode::Holding => pb::SampleFlags::Holding as u32,
        LoopMode::Local => pb::SampleFlags::Fallback as u32,
        LoopMode::SafeStop => pb::SampleFlags::SafeStop as u32,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_command_mode_maps_to_its_body_and_unknown_ones_to_unknown() {
        let mut cmd = pb::Command {
            seq: 7,
            mode: pb::Mode::Control as i32,
            v: vec![1.0, -2.0],
            horizon: vec![3.0, 4.0],
            error: "too fast".into(),
            ..Default::default()
        };
        let c = IncomingCommand::from_wire(&cmd);
        assert_eq!(c.seq, 7);
        assert_eq!(c.body, CommandBody::Control(&[1.0, -2.0]));
        assert_eq!(c.horizon, &[3.0, 4.0]);
        cmd.mode = pb::Mode::WarmingUp as i32;
        assert_eq!(
            IncomingCommand::from_wire(&cmd).body,
            CommandBody::WarmingUp
        );
        cmd.mode = pb::Mode::Rejected as i32;
        assert_eq!(
            IncomingCommand::from_wire(&cmd).body,
            CommandBody::Rejected("too fast")
        );
        for mode in [pb::Mode::Unspecified as i32, pb::Mode::Stale as i32, 99, -1] {
            cmd.mode = mode;
            assert_eq!(IncomingCommand::from_wire(&cmd).body, CommandBody::Unknown);
        }
    }

    /// The service tells the modes apart by these flags alone: remote is none, and every
    /// other mode one flag of its own.
    #[test]
    fn each_mode_has_its_own_flag_and_remote_none() {
        let flags: Vec<u32> = [
            LoopMode::Remote,
            LoopMode::Holding,
            LoopMode::Local,
            LoopMode::SafeStop,
        ]
        .into_iter()
        .map(sample_flags)
        .collect();
        assert_eq!(flags[0], 0);
        for (i, f) in flags.iter().enumerate().skip(1) {
            assert_eq!(f.count_ones(), 1, "mode {i}: one flag, not {f:#b}");
            assert!(
                flags[i + 1..].iter().all(|g| g != f),
                "mode {i} shares {f:#b}"
            );
        }
        assert_eq!(flags[2], pb::SampleFlags::Fallback as u32);
    }
}
