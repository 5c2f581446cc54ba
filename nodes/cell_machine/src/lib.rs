//! The polar cell's machine, whatever runs it.
//!
//! A print's plan (step segments from the planner, screw commands from the screw driver) is
//! executed by a *machine backend*: the virtual executor (`cell_executor`, the machine in
//! software) or a microcontroller behind the bridge (`mcu_bridge`). Both look the same from
//! the ROS graph — the same `/joint_states`, `/tf`, plan credit, `/diagnostics`, the same
//! `/cell/*` services, the same print action on top — because one node loop ([`node`],
//! feature `node`) drives any [`Machine`]. A backend decides how the plan is played; the loop
//! decides nothing but when to ask.
//!
//! * [`Machine`] — what a backend does: take the plan, run to "now", report its state, obey
//!   pause, resume, cancel, emergency stop and reset;
//! * [`node`] — the loop: messages and the clock in, the machine's state out (its `/tf` from
//!   the URDF by `cell_runtime::tf`, which the machining head's node shares).

#[cfg(feature = "node")]
pub mod node;

use polar_cell_msgs::{ScrewCommand, StepSegment};

/// Where the machine is in its life.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum PlayerState {
    /// Nothing to play: not started, finished, or starved.
    Idle,
    /// Playing segments (σ may be below 1 while a hold or resume is under way).
    Running,
    /// Held on the path: σ = 0 with segments still to play.
    Held,
    /// Stopped at once (emergency stop or a fault): nothing plays until a reset.
    Stopped,
}

/// Why the feed is being held.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum HoldReason {
    /// Asked for (pause); lasts until a resume.
    Pause,
    /// Asked for, and what is queued is dropped once at rest.
    Cancel,
    /// The queued plan ran short; resumes by itself when enough has arrived.
    Underrun,
}

/// The executed state of a machine now.
#[derive(Clone, Debug, PartialEq)]
pub struct MachineState {
    /// `bed_theta` (rad), `arm_r` (m), `z` (m), `screw` (rad): the URDF's four joints.
    pub positions: [f64; 4],
    /// Their velocities (rad/s, m/s, m/s, rad/s).
    pub velocities: [f64; 4],
    pub screw_rpm: f64,
    pub pin_open: bool,
    pub state: PlayerState,
    pub hold: Option<HoldReason>,
    /// Feed scale σ.
    pub feed: f64,
    /// Machine time since the first tick (s) and plan time executed (s).
    pub machine_time_s: f64,
    pub plan_time_s: f64,
    /// The move and G-code line playing now.
    pub current: Option<(u64, u32)>,
    /// Machine time (ns) at which `positions` and `velocities` were measured, when that is
    /// not "now": a microcontroller reports its counts as of its last state message, and
    /// they are exact for that instant, not for the host's.
    pub measured_ns: Option<i64>,
}

/// A machine that executes the plan. Times are nanoseconds of the caller's machine clock
/// (monotonic; the first tick is machine time 0).
///
/// Errors are the backend's own, shown to the user as they are: the node loop treats any
/// error as a fault (the machine goes to its safe state and the print ends with the reason).
pub trait Machine {
    type Error: std::fmt::Display;

    /// Queue a planned step segment (there is room: see [`Machine::free_slots`]).
    fn on_segment(&mut self, msg: &StepSegment) -> Result<(), Self::Error>;
    /// Queue a screw command.
    fn on_screw(&mut self, msg: &ScrewCommand) -> Result<(), Self::Error>;
    /// Free places for step segments and screw commands.
    fn free_slots(&self) -> (usize, usize);
    /// The plan is complete: it ends at rest where it ends.
    fn finish_input(&mut self);
    /// Execute (or follow the execution) up to machine time `now_ns`.
    fn on_tick(&mut self, now_ns: i64) -> Result<(), Self::Error>;
    /// The executed state at the last tick.
    fn state(&self) -> MachineState;
    /// The stamp of plan time 0 on the producers' clock, once the first segment told it.
    fn epoch_ns(&self) -> Option<i64>;
    /// Nothing left to play: idle, with nothing queued or playing.
    fn is_drained(&self) -> bool;
    /// Plan time queued ahead of execution (s).
    fn plan_ahead_s(&self) -> f64;
    /// Segments completed, and the move and G-code line of the last one.
    fn completed(&self) -> (u64, Option<(u64, u32)>);
    /// Times the plan ran short (the machine held on the path for lack of plan).
    fn underruns(&self) -> u64;
    /// Slow to rest along the path and hold.
    fn pause(&mut self);
    /// Leave a pause: the pin reopens, after its delay the machine speeds back up.
    fn resume(&mut self);
    /// Slow to rest along the path, then drop the rest of the plan.
    fn cancel(&mut self);
    /// Stop stepping at once, screw stopped, pin closed; stays stopped until a reset.
    fn emergency_stop(&mut self);
    /// Leave an emergency stop or fault, ready for a new plan.
    fn reset(&mut self);
    /// What else `/diagnostics` should say about this backend (key, value).
    fn diagnostics(&self) -> Vec<(&'static str, String)> {
        Vec::new()
    }
    /// Machine time 0 (every `now_ns` given) is the wall instant `origin`, and it runs `speed`
    /// times wall time: for a backend that stamps what it receives as it arrives.
    fn clock_started(&mut self, _origin: std::time::Instant, _speed: f64) {}
}
