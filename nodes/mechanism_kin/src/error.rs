//! The one error type of the kinematics core: each variant carries the values that explain it.

/// Why a kinematic request has no valid answer.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum KinError {
    #[error("input is not finite: {what} = {value}")]
    NotFinite { what: &'static str, value: f64 },
    #[error(
        "chain {chain}: leg length {length_mm:.6} mm is outside [{min_mm:.3}, {max_mm:.3}] mm"
    )]
    LegOutOfRange {
        chain: usize,
        length_mm: f64,
        min_mm: f64,
        max_mm: f64,
    },
    #[error(
        "chain {chain}: spherical joint swing {swing_deg:.4}° exceeds its ±{max_deg:.1}° limit"
    )]
    SwingLimit {
        chain: usize,
        swing_deg: f64,
        max_deg: f64,
    },
    #[error(
        "tool tip {axis} = {tip_mm} mm is out of reach: the table travels ±{table_max_mm:.3} mm \
         and the platform shifts less than its {platform_radius_mm:.3} mm radius"
    )]
    TipOutOfReach {
        axis: char,
        tip_mm: f64,
        table_max_mm: f64,
        platform_radius_mm: f64,
    },
    #[error("table {axis}: {position_mm:.6} mm is outside ±{max_mm:.3} mm")]
    TableLimit {
        axis: char,
        position_mm: f64,
        max_mm: f64,
    },
    #[error("tilt {tilt_deg:.4}° is beyond the mechanism's ±{max_deg:.1}°")]
    TiltLimit { tilt_deg: f64, max_deg: f64 },
    #[error(
        "tool axis ({x}, {y}, {z}) is not a unit vector pointing up (spindle-ward): |a| = {norm}"
    )]
    BadToolAxis { x: f64, y: f64, z: f64, norm: f64 },
    #[error("forward kinematics did not converge in {iterations} iterations (side residual {residual_mm:.3e} mm)")]
    NotConverged { iterations: u32, residual_mm: f64 },
    #[error("forward kinematics diverged at iteration {iterations}: leg lengths ({l1:.6}, {l2:.6}, {l3:.6}) mm close no platform")]
    Unreachable {
        iterations: u32,
        l1: f64,
        l2: f64,
        l3: f64,
    },
    #[error("forward kinematics found the mirrored assembly (platform normal z = {normal_z:.6}), not the machine's")]
    WrongAssembly { normal_z: f64 },
    #[error("singular configuration: {what} (condition estimate {condition:.3e})")]
    Singular { what: &'static str, condition: f64 },
}

/// Check that a value is finite, naming it in the error.
pub(crate) fn finite(what: &'static str, value: f64) -> Result<f64, KinError> {
    if value.is_finite() {
        Ok(value)
    } else {
        Err(KinError::NotFinite { what, value })
    }
}
