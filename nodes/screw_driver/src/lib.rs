//! Screw extruder control (seed 000 §2, §4, §5.3).

pub mod fir;
