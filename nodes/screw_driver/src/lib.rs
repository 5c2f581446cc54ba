//! Screw extruder control (seed 000 §2, §4, §5.3): pin and rpm commands from moves and the
//! planned timeline, and the seed's Kaiser-window smoothing.
//!
//! Pure: no DDS. The node (feature `node`) wires it to topics.

pub mod compensation;
pub mod extruder;
pub mod fir;
pub mod flow;
pub mod joint;
pub mod reduced;
pub mod screw;
pub mod stream;

#[cfg(feature = "node")]
pub mod node;
