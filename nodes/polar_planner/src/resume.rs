//! What a planner node acknowledges with, so that a restarted one continues its timeline.
//!
//! The node acknowledges a move to the streamer once its plan is published; with the
//! acknowledgement goes a [`Checkpoint`]: the [`ResumePoint`] of that move, the step position
//! after its segments, the plan's epoch and the sampling clock. The streamer keeps the latest
//! and hands it back with the resume point (`cell_runtime::flow`). A planner started again
//! mid-print continues from it — the same plan clock, joints, path speed and step position —
//! so the machine receives the moves after it as if nothing had happened, instead of a second
//! plan starting at time 0 from the origin.
//!
//! The bytes are the CDR encoding of [`Checkpoint`] (the encoding of every message here), led
//! by a format number, and carry a digest of the planner's options: a planner started with
//! other options (another URDF, other step rates) would plan another timeline, and refuses.

use polar_cell_msgs::checkpoint::{self, CheckpointHeader, ResumeStateError};
use serde::{Deserialize, Serialize};

use crate::steps::StepOptions;
use crate::{PlannerOptions, ResumePoint, TrajPoint};

/// The format this build writes and reads.
pub const CHECKPOINT_FORMAT: u32 = 1;

/// A planner node's state after every move before `next_sequence` was published.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Checkpoint {
    /// Format, the first move not yet published (the acknowledged point), and the
    /// [`options_digest`] of the planner that wrote it.
    pub header: CheckpointHeader,
    /// Stamp of plan time 0 (ns). With `t_s`, the plan's reach that a machine reads from
    /// the lead of these bytes (`polar_cell_msgs::checkpoint::PlannerReach`): keep them first.
    pub plan_epoch_ns: i64,
    pub t_s: f64,
    pub path_speed2: f64,
    pub q: [f64; 3],
    pub p_m: [f64; 3],
    pub last_t_s: f64,
    pub last_q: [f64; 3],
    pub last_qd: [f64; 3],
    pub last_qdd: [f64; 3],
    pub last_tool_speed: f64,
    pub previous_extruding: bool,
    /// Absolute step position after the published segments.
    pub step_position: [i64; 3],
    /// Plan time of the next planned joint-state sample (s).
    pub next_sample_t_s: f64,
    pub moves_planned: u64,
}

/// Why acknowledged bytes are not a checkpoint this planner can continue from.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum CheckpointError {
    #[error(transparent)]
    State(#[from] ResumeStateError),
    #[error("resume state holds a value that is not a plan state: {0}")]
    NotAPlanState(String),
}

impl checkpoint::Checkpoint for Checkpoint {
    const FORMAT: u32 = CHECKPOINT_FORMAT;
    const WRITER: &'static str = "planner";
    const OTHER_OPTIONS_WOULD: &'static str = "it would plan another timeline";
    fn header(&self) -> &CheckpointHeader {
        &self.header
    }
}

impl Checkpoint {
    /// The checkpoint after a published move `plan_resume` (its [`crate::PlannedMove::resume`]).
    pub fn new(
        next_sequence: u64,
        options_digest: u64,
        plan_epoch_ns: i64,
        at: &ResumePoint,
        step_position: [i64; 3],
        next_sample_t_s: f64,
        moves_planned: u64,
    ) -> Checkpoint {
        Checkpoint {
            header: <Checkpoint as checkpoint::Checkpoint>::header_for(
                next_sequence,
                options_digest,
            ),
            plan_epoch_ns,
            t_s: at.t_s,
            path_speed2: at.path_speed2,
            q: at.q,
            p_m: at.p_m,
            last_t_s: at.last_point.t,
            last_q: at.last_point.q,
            last_qd: at.last_point.qd,
            last_qdd: at.last_point.qdd,
            last_tool_speed: at.last_point.tool_speed,
            previous_extruding: at.previous_extruding,
            step_position,
            next_sample_t_s,
            moves_planned,
        }
    }

    /// Where the planner resumes.
    pub fn resume_point(&self) -> ResumePoint {
        ResumePoint {
            t_s: self.t_s,
            path_speed2: self.path_speed2,
            q: self.q,
            p_m: self.p_m,
            last_point: TrajPoint {
                t: self.last_t_s,
                q: self.last_q,
                qd: self.last_qd,
                qdd: self.last_qdd,
                tool_speed: self.last_tool_speed,
            },
            previous_extruding: self.previous_extruding,
        }
    }

    pub fn to_bytes(&self) -> Vec<u8> {
        checkpoint::to_bytes(self)
    }

    /// Read the checkpoint acknowledged at `resume_point` by a planner whose options have
    /// `options_digest`, refusing anything else.
    pub fn from_bytes(
        bytes: &[u8],
        resume_point: u64,
        options_digest: u64,
    ) -> Result<Checkpoint, CheckpointError> {
        let c: Checkpoint = checkpoint::from_bytes(bytes, resume_point, options_digest)?;
        let floats = [
            c.t_s,
            c.path_speed2,
            c.last_t_s,
            c.last_tool_speed,
            c.next_sample_t_s,
        ]
        .into_iter()
        .chain(c.q)
        .chain(c.p_m)
        .chain(c.last_q)
        .chain(c.last_qd)
        .chain(c.last_qdd);
        if let Some(bad) = floats.into_iter().find(|x| !x.is_finite()) {
            return Err(CheckpointError::NotAPlanState(format!("{bad}")));
        }
        if c.t_s < 0.0 || c.path_speed2 < 0.0 || c.plan_epoch_ns < 0 {
            return Err(CheckpointError::NotAPlanState(format!(
                "plan time {} s, path speed² {}, epoch {} ns",
                c.t_s, c.path_speed2, c.plan_epoch_ns
            )));
        }
        Ok(c)
    }
}

/// A digest of everything that shapes the plan and its steps (FNV-1a over the options' exact
/// `Debug` text: every float printed so that it reads back the same).
pub fn options_digest(planner: &PlannerOptions, steps: &StepOptions) -> u64 {
    checkpoint::options_digest(&format!("{planner:?} {steps:?}"))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample() -> Checkpoint {
        let at = ResumePoint {
            t_s: 12.5,
            path_speed2: 0.0004,
            q: [7.0 * std::f64::consts::PI + 0.1, 0.05, 0.002],
            p_m: [0.01, -0.02, 0.002],
            last_point: TrajPoint {
                t: 12.5,
                q: [1.0, 2.0, 3.0],
                qd: [0.1, 0.2, 0.3],
                qdd: [-1.0, 0.0, 1.0],
                tool_speed: 0.02,
            },
            previous_extruding: true,
        };
        Checkpoint::new(42, 7, 1_700_000_000_000_000_000, &at, [1, -2, 3], 12.52, 40)
    }

    /// A machine reads where the plan ends from the lead of these bytes.
    #[test]
    fn a_checkpoint_leads_with_the_plans_reach() {
        let c = sample();
        let (header, reach) = checkpoint::reach::<checkpoint::PlannerReach>(&c.to_bytes()).unwrap();
        assert_eq!(header, c.header);
        assert_eq!(reach.plan_epoch_ns, c.plan_epoch_ns);
        assert_eq!(reach.t_s.to_bits(), c.t_s.to_bits());
    }

    #[test]
    fn a_checkpoint_reads_back_exactly() {
        let c = sample();
        let back = Checkpoint::from_bytes(&c.to_bytes(), 42, 7).unwrap();
        assert_eq!(back, c);
        assert_eq!(back.resume_point().q[0].to_bits(), c.q[0].to_bits());
    }

    #[test]
    fn another_point_other_options_or_garbage_are_refused_by_name() {
        let bytes = sample().to_bytes();
        assert_eq!(
            Checkpoint::from_bytes(&bytes, 43, 7),
            Err(CheckpointError::State(ResumeStateError::WrongPoint {
                expected: 43,
                found: 42
            }))
        );
        assert!(matches!(
            Checkpoint::from_bytes(&bytes, 42, 8),
            Err(CheckpointError::State(
                ResumeStateError::OtherOptions { .. }
            ))
        ));
        let e = Checkpoint::from_bytes(&bytes[..20], 42, 7).unwrap_err();
        assert!(e.to_string().contains("20 bytes"), "{e}");
        let mut nan = sample();
        nan.path_speed2 = f64::NAN;
        assert!(matches!(
            Checkpoint::from_bytes(&nan.to_bytes(), 42, 7),
            Err(CheckpointError::NotAPlanState(_))
        ));
        let mut future = sample();
        future.header.format = 9;
        assert!(matches!(
            Checkpoint::from_bytes(&future.to_bytes(), 42, 7),
            Err(CheckpointError::State(ResumeStateError::Format {
                found: 9,
                ..
            }))
        ));
    }

    #[test]
    fn the_digest_tells_options_apart() {
        let a = PlannerOptions::default();
        let s = StepOptions::default();
        let mut b = a.clone();
        b.path_tolerance_m *= 1.0 + f64::EPSILON;
        assert_eq!(options_digest(&a, &s), options_digest(&a.clone(), &s));
        assert_ne!(options_digest(&a, &s), options_digest(&b, &s));
    }
}
