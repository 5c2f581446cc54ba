//! The executor of the polar cell: the machine itself, in software.
//!
//! The planner sends step segments (`/polar/steps`) and the screw driver screw commands
//! (`/screw/command`), both ahead of time. The executor plays them on a monotonic clock: it
//! regenerates every pulse with the same fixed-point [`step_core`] a microcontroller runs, so
//! the executed position at any instant is the step count reached by then, and the screw's
//! angle integrates the rpm actually executed.
//!
//! * [`player`] — the segment queue and the pulse clock: position, velocity, underrun, e-stop;
//! * [`screw`] — screw commands on the plan timeline, executed as time passes;
//! * [`session`] — both joined on one plan clock: messages in, the executed state out;
//!
//! Pure: no DDS, no clock of its own — the caller says what time it is. The DDS node
//! ([`node`], feature `node`) feeds it messages and the monotonic clock.

#[cfg(feature = "node")]
pub mod node;
pub mod player;
pub mod screw;
pub mod session;

/// Seconds as Q32 timer ticks of a `timer_hz` timer (rounded; ≥ 0 assumed).
pub(crate) fn seconds_to_q32(seconds: f64, timer_hz: f64) -> u128 {
    (seconds * timer_hz * step_core::ONE_TICK_Q32 as f64).round() as u128
}

/// Q32 timer ticks of a `timer_hz` timer as seconds.
pub(crate) fn q32_to_seconds(q32: u128, timer_hz: f64) -> f64 {
    q32 as f64 / step_core::ONE_TICK_Q32 as f64 / timer_hz
}

pub use cell_machine::MachineState;
pub use player::{Edge, HoldReason, Player, PlayerError, PlayerOptions, PlayerState, SegmentJob};
pub use screw::ScrewTrack;
pub use session::{ExecError, Executor, ExecutorOptions};
