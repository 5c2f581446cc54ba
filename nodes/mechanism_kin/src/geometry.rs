//! Dimensions and limits of the 3-RPS + XY-table mechanism (SPEC §5).
//!
//! Three identical chains stand at angles ψ_i (seed: 270°, 30°, 150°). Chain i has its base
//! hinge A_i on the base circle (radius R_in) turning about the circle's tangent, so the leg
//! moves in the vertical plane through the z axis and the radial direction u_i. Its spherical
//! joint C_i sits on the platform circle (radius R_out) at the same angle in the platform
//! frame. The output point P is the platform centre; the tool tip hangs `tool_length_mm` below
//! it along the platform normal. The defaults are the seed's machine; the node reads them from
//! `urdf/hybrid_pkm.urdf` instead.

use nalgebra::Vector3;

/// Joint limits of the mechanism.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Limits {
    /// Shortest leg (hinge A_i to sphere centre C_i), mm.
    pub leg_min_mm: f64,
    /// Longest leg, mm: `leg_min_mm` + the 450 mm ball-screw stroke.
    pub leg_max_mm: f64,
    /// Largest swing of each spherical joint (leg axis against platform normal), rad.
    pub swing_max_rad: f64,
    /// Table travel, ± mm in X and in Y.
    pub table_max_mm: f64,
    /// Largest platform tilt θ2 of the work range, rad (seed §2.5.5: 20°).
    pub tilt_max_rad: f64,
}

/// The mechanism's geometry with the vectors derived from it.
#[derive(Debug, Clone, PartialEq)]
pub struct Geometry {
    /// R_in: radius of the base hinge circle, mm.
    pub base_radius_mm: f64,
    /// R_out: radius of the platform sphere circle, mm.
    pub platform_radius_mm: f64,
    /// ψ_1, the angle of chain 1 (the others follow at +120° and +240°), rad.
    pub chain1_angle_rad: f64,
    /// Output point to tool tip, mm.
    pub tool_length_mm: f64,
    pub limits: Limits,
    /// u_i: unit radial direction of chain i.
    pub radial: [Vector3<f64>; 3],
    /// t_i = ẑ × u_i: the hinge axis direction and the normal of chain i's plane.
    pub tangent: [Vector3<f64>; 3],
    /// A_i, base frame, mm.
    pub base_points: [Vector3<f64>; 3],
    /// p_i, platform frame, mm.
    pub platform_points: [Vector3<f64>; 3],
}

/// The seed's machine: R_in 330 mm, R_out 316 mm, chains at 270°/30°/150°, 100 mm tool,
/// 450 mm leg stroke, ±45° spherical joints, ±75 mm table.
pub const SEED_BASE_RADIUS_MM: f64 = 330.0;
pub const SEED_PLATFORM_RADIUS_MM: f64 = 316.0;
pub const SEED_TOOL_LENGTH_MM: f64 = 100.0;
/// Leg stroke 450 mm, placed so the seed's work range (tool tip Z 156–356 mm, tilt ±20°)
/// lies inside it with margin at both ends (the range needs 148.1–559.7 mm).
pub const SEED_LEG_MIN_MM: f64 = 130.0;
pub const SEED_LEG_STROKE_MM: f64 = 450.0;

impl Default for Geometry {
    fn default() -> Self {
        Geometry::new(
            SEED_BASE_RADIUS_MM,
            SEED_PLATFORM_RADIUS_MM,
            270f64.to_radians(),
            SEED_TOOL_LENGTH_MM,
            Limits {
                leg_min_mm: SEED_LEG_MIN_MM,
                leg_max_mm: SEED_LEG_MIN_MM + SEED_LEG_STROKE_MM,
                swing_max_rad: 45f64.to_radians(),
                table_max_mm: 75.0,
                tilt_max_rad: 20f64.to_radians(),
            },
        )
    }
}

impl Geometry {
    /// Build the geometry and its derived vectors.
    pub fn new(
        base_radius_mm: f64,
        platform_radius_mm: f64,
        chain1_angle_rad: f64,
        tool_length_mm: f64,
        limits: Limits,
    ) -> Self {
        let angle = |i: usize| chain1_angle_rad + i as f64 * 2.0 * std::f64::consts::FRAC_PI_3;
        let radial: [Vector3<f64>; 3] = std::array::from_fn(|i| {
            // Snap the rounding residue of cos 270° etc. to the exact zero of the layout.
            let snap = |v: f64| if v.abs() < 1e-15 { 0.0 } else { v };
            let (s, c) = angle(i).sin_cos();
            Vector3::new(snap(c), snap(s), 0.0)
        });
        let tangent = radial.map(|u| Vector3::new(-u.y, u.x, 0.0));
        Geometry {
            base_radius_mm,
            platform_radius_mm,
            chain1_angle_rad,
            tool_length_mm,
            limits,
            radial,
            tangent,
            base_points: radial.map(|u| u * base_radius_mm),
            platform_points: radial.map(|u| u * platform_radius_mm),
        }
    }

    /// ψ_i, the angle of chain i (0-based), rad.
    pub fn chain_angle_rad(&self, chain: usize) -> f64 {
        self.chain1_angle_rad + chain as f64 * 2.0 * std::f64::consts::FRAC_PI_3
    }

    /// The side of the platform triangle, √3·R_out.
    pub fn platform_side_mm(&self) -> f64 {
        3f64.sqrt() * self.platform_radius_mm
    }
}
