//! The polar cell's microcontroller, without its hardware.
//!
//! Everything the firmware decides lives here, `no_std`, without allocation and without
//! floating point, so that the RP2040 build, the host-side MCU emulator and these tests run
//! the very same code:
//!
//! * [`machine`] — the bounded segment queue on the plan clock, pulses from the shared
//!   [`step_core`] (the arithmetic the planner's decoder and the executor use), feed hold and
//!   resume along the path, step positions, the screw and pin ([`screw`]), and faults: a late
//!   or discontinuous segment, an underrun, a silent host, an emergency stop. A fault stops
//!   every output at once and is latched until the host resets it.
//! * [`outputs`] — step edges to pin writes: step/dir drivers or a unipolar motor's four
//!   coils (seed 001's bench rig).
//! * [`endpoint`] — the MCU's end of [`cell_protocol`]: bytes in, replies and state out.
//! * [`seed_program`] — seed 001's bench program (six linear moves on the start switch) and
//!   its `X:..,Y:..,Z:..` position lines.
//!
//! The hardware layer only moves bytes between its UART/USB and [`Endpoint`], and step edges
//! from [`Machine::advance`] to its pins at their ticks.

#![no_std]
#![forbid(unsafe_code)]

pub mod endpoint;
pub mod machine;
pub mod outputs;
pub mod screw;
pub mod seed_program;

pub use endpoint::Endpoint;
pub use machine::{Machine, MachineConfig, StepEdge};
