//! Platform poses.
//!
//! The mechanism has three degrees of freedom: height Z of the output point and a tilt. The
//! seed writes the tilt as θ2 about the horizontal axis (cos θ1, sin θ1, 0) (eq. 3.3) or as
//! roll/pitch with a dependent yaw (eq. 3.14, 3.24). Both are the same set of rotations: tilts
//! with zero torsion. (θ1, θ2) are polar coordinates and lose θ1 at θ2 = 0, so inside we use
//! the tilt vector w = θ2·(cos θ1, sin θ1): the rotation vector of the tilt, smooth everywhere.

use nalgebra::{Matrix3, Vector3};

/// A zero-torsion tilt, as its rotation vector (w_x, w_y, 0), rad.
#[derive(Debug, Clone, Copy, PartialEq, Default, serde::Serialize, serde::Deserialize)]
pub struct Tilt {
    pub wx_rad: f64,
    pub wy_rad: f64,
}

/// A platform pose: output-point height and tilt.
#[derive(Debug, Clone, Copy, PartialEq, Default, serde::Serialize, serde::Deserialize)]
pub struct Pose {
    pub z_mm: f64,
    pub tilt: Tilt,
}

/// sin θ / θ, (1 − cos θ)/θ² and their derivatives divided by θ, all smooth at θ = 0.
#[derive(Debug, Clone, Copy)]
pub(crate) struct TiltScalars {
    pub sin_c: f64,
    pub one_minus_cos_c: f64,
    pub d_sin_c: f64,
    pub d_one_minus_cos_c: f64,
    pub cos: f64,
}

impl TiltScalars {
    /// For θ² = w_x² + w_y²; power series below θ = 0.1 where the closed forms cancel.
    pub fn new(theta_sq: f64) -> Self {
        let t2 = theta_sq;
        if t2 < 1e-2 {
            let t4 = t2 * t2;
            let t6 = t4 * t2;
            let t8 = t4 * t4;
            TiltScalars {
                sin_c: 1.0 - t2 / 6.0 + t4 / 120.0 - t6 / 5040.0 + t8 / 362_880.0,
                one_minus_cos_c: 0.5 - t2 / 24.0 + t4 / 720.0 - t6 / 40_320.0 + t8 / 3_628_800.0,
                d_sin_c: -1.0 / 3.0 + t2 / 30.0 - t4 / 840.0 + t6 / 45_360.0 - t8 / 3_991_680.0,
                d_one_minus_cos_c: -1.0 / 12.0 + t2 / 180.0 - t4 / 6720.0 + t6 / 453_600.0
                    - t8 / 47_900_160.0,
                cos: 1.0 - t2 / 2.0 + t4 / 24.0 - t6 / 720.0 + t8 / 40_320.0,
            }
        } else {
            let t = t2.sqrt();
            let (s, c) = t.sin_cos();
            let omc = 2.0 * (0.5 * t).sin().powi(2);
            TiltScalars {
                sin_c: s / t,
                one_minus_cos_c: omc / t2,
                d_sin_c: (t * c - s) / (t2 * t),
                d_one_minus_cos_c: (t * s - 2.0 * omc) / (t2 * t2),
                cos: c,
            }
        }
    }
}

impl Tilt {
    /// From the seed's θ1 (direction of the tilt axis) and θ2 (tilt about it).
    pub fn from_theta(theta1_rad: f64, theta2_rad: f64) -> Self {
        let (s1, c1) = theta1_rad.sin_cos();
        Tilt {
            wx_rad: theta2_rad * c1,
            wy_rad: theta2_rad * s1,
        }
    }

    /// The seed's (θ1, θ2) with θ1 ∈ (0, π] and θ2 signed (seed §2.5.5). At θ2 = 0, θ1 is
    /// undefined and reported as π.
    pub fn theta(&self) -> (f64, f64) {
        let theta2 = self.wx_rad.hypot(self.wy_rad);
        let theta1 = self.wy_rad.atan2(self.wx_rad);
        if theta1 <= 0.0 {
            (theta1 + std::f64::consts::PI, -theta2)
        } else {
            (theta1, theta2)
        }
    }

    /// Tilt angle |θ2|, rad.
    pub fn angle_rad(&self) -> f64 {
        self.wx_rad.hypot(self.wy_rad)
    }

    /// The tilt whose platform normal is `normal` (need not be unit; must point up).
    pub fn from_normal(normal: &Vector3<f64>) -> Self {
        let n = normal.normalize();
        let sin_theta = n.x.hypot(n.y);
        let theta = sin_theta.atan2(n.z);
        // w = θ/sin θ · (−n_y, n_x); θ/sin θ → 1 at the vertical.
        let scale = if sin_theta < 1e-12 {
            1.0
        } else {
            theta / sin_theta
        };
        Tilt {
            wx_rad: -n.y * scale,
            wy_rad: n.x * scale,
        }
    }

    /// Roll/pitch form (seed eq. 3.14): D = Rx(α)·Ry(β)·Rz(γ_u) with the dependent yaw
    /// γ_u = −atan(sin α sin β / (cos α + cos β)) (sign corrected, SPEC §9).
    pub fn from_roll_pitch(roll_rad: f64, pitch_rad: f64) -> Self {
        let (sa, ca) = roll_rad.sin_cos();
        let (sb, cb) = pitch_rad.sin_cos();
        // Normal D·ẑ = (sin β, −sin α cos β, cos α cos β): yaw does not move it.
        Tilt::from_normal(&Vector3::new(sb, -sa * cb, ca * cb))
    }

    /// The parasitic yaw γ_u of the roll/pitch form.
    pub fn parasitic_yaw(roll_rad: f64, pitch_rad: f64) -> f64 {
        -(roll_rad.sin() * pitch_rad.sin()).atan2(roll_rad.cos() + pitch_rad.cos())
    }

    /// The rotation matrix (Rodrigues, seed eq. 3.3).
    pub fn rotation(&self) -> Matrix3<f64> {
        let (a, b) = (self.wx_rad, self.wy_rad);
        let k = TiltScalars::new(a * a + b * b);
        let (s, f) = (k.sin_c, k.one_minus_cos_c);
        Matrix3::new(
            1.0 - f * b * b,
            f * a * b,
            s * b,
            f * a * b,
            1.0 - f * a * a,
            -s * a,
            -s * b,
            s * a,
            k.cos,
        )
    }

    /// The platform normal R·ẑ, which is the tool axis pointing spindle-ward.
    pub fn normal(&self) -> Vector3<f64> {
        let (a, b) = (self.wx_rad, self.wy_rad);
        let k = TiltScalars::new(a * a + b * b);
        Vector3::new(k.sin_c * b, -k.sin_c * a, k.cos)
    }

    /// Roll and pitch (α, β) of this tilt in the form D = Rx(α)·Ry(β)·Rz(γ_u).
    pub fn roll_pitch(&self) -> (f64, f64) {
        let n = self.normal();
        let pitch = n.x.clamp(-1.0, 1.0).asin();
        let roll = (-n.y).atan2(n.z);
        (roll, pitch)
    }
}

impl Pose {
    /// From the seed's (Z, θ1, θ2).
    pub fn from_theta(z_mm: f64, theta1_rad: f64, theta2_rad: f64) -> Self {
        Pose {
            z_mm,
            tilt: Tilt::from_theta(theta1_rad, theta2_rad),
        }
    }

    /// From (Z, roll, pitch).
    pub fn from_roll_pitch(z_mm: f64, roll_rad: f64, pitch_rad: f64) -> Self {
        Pose {
            z_mm,
            tilt: Tilt::from_roll_pitch(roll_rad, pitch_rad),
        }
    }

    /// Linear interpolation in (Z, w): the ideal path between two poses.
    pub fn lerp(&self, other: &Pose, s: f64) -> Pose {
        Pose {
            z_mm: self.z_mm + s * (other.z_mm - self.z_mm),
            tilt: Tilt {
                wx_rad: self.tilt.wx_rad + s * (other.tilt.wx_rad - self.tilt.wx_rad),
                wy_rad: self.tilt.wy_rad + s * (other.tilt.wy_rad - self.tilt.wy_rad),
            },
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Seed eq. 3.3 written out in θ1, θ2.
    fn seed_rotation(t1: f64, t2: f64) -> Matrix3<f64> {
        let (s1, c1) = t1.sin_cos();
        let (s2, c2) = t2.sin_cos();
        Matrix3::new(
            c1 * c1 + c2 - c1 * c1 * c2,
            c1 * s1 - c1 * s1 * c2,
            s1 * s2,
            c1 * s1 - c1 * s1 * c2,
            s1 * s1 + c2 - s1 * s1 * c2,
            -c1 * s2,
            -s1 * s2,
            c1 * s2,
            c2,
        )
    }

    #[test]
    fn rotation_matches_seed_rodrigues_on_both_sides_of_the_series_switch() {
        for &t2 in &[0.0, 1e-7, 0.05, 0.0999, 0.1001, 0.2, 0.35, -0.3] {
            for &t1 in &[0.1, 0.7, 1.5, 2.9, 3.1] {
                let r = Tilt::from_theta(t1, t2).rotation();
                let d = (r - seed_rotation(t1, t2)).abs().max();
                assert!(d < 2e-16 * 8.0, "θ1 {t1} θ2 {t2}: {d:e}");
                assert!((r.transpose() * r - Matrix3::identity()).abs().max() < 1e-15);
            }
        }
    }

    #[test]
    fn series_derivatives_match_finite_differences() {
        for &t in &[1e-3, 0.05, 0.09, 0.11, 0.3] {
            let h = 1e-6;
            let k = TiltScalars::new(t * t);
            let kp = TiltScalars::new((t + h) * (t + h));
            let km = TiltScalars::new((t - h) * (t - h));
            let ds = (kp.sin_c - km.sin_c) / (2.0 * h) / t;
            let df = (kp.one_minus_cos_c - km.one_minus_cos_c) / (2.0 * h) / t;
            assert!((ds - k.d_sin_c).abs() < 1e-7, "{t}: {ds} vs {}", k.d_sin_c);
            assert!((df - k.d_one_minus_cos_c).abs() < 1e-7, "{t}");
            assert!((k.sin_c - t.sin() / t).abs() < 1e-15);
            assert!((k.cos - t.cos()).abs() < 1e-15);
        }
    }

    #[test]
    fn theta_round_trip_and_normalisation() {
        let (t1, t2) = Tilt::from_theta(0.5, 0.2).theta();
        assert!((t1 - 0.5).abs() < 1e-15 && (t2 - 0.2).abs() < 1e-15);
        // θ1 = 0 is reported as θ1 = 180° with θ2 negated: the same tilt.
        let (t1, t2) = Tilt::from_theta(0.0, 0.2).theta();
        assert!((t1 - std::f64::consts::PI).abs() < 1e-15 && (t2 + 0.2).abs() < 1e-15);
        let (t1, t2) = Tilt::from_theta(-0.5, 0.2).theta();
        assert!((t1 - (std::f64::consts::PI - 0.5)).abs() < 1e-15 && (t2 + 0.2).abs() < 1e-15);
    }

    #[test]
    fn roll_pitch_with_corrected_yaw_is_the_same_rotation() {
        for &(a, b) in &[
            (0.1, 0.2),
            (-0.3, 0.15),
            (0.25, -0.25),
            (0.0, 0.3),
            (0.2, 0.0),
        ] {
            let g = Tilt::parasitic_yaw(a, b);
            let d = nalgebra::Rotation3::from_axis_angle(&Vector3::x_axis(), a)
                * nalgebra::Rotation3::from_axis_angle(&Vector3::y_axis(), b)
                * nalgebra::Rotation3::from_axis_angle(&Vector3::z_axis(), g);
            let r = Tilt::from_roll_pitch(a, b).rotation();
            let diff = (r - d.matrix()).abs().max();
            assert!(diff < 1e-15, "({a}, {b}): {diff:e}");
            // With the seed's printed sign (+atan) the rotation is a different one.
            let wrong = nalgebra::Rotation3::from_axis_angle(&Vector3::x_axis(), a)
                * nalgebra::Rotation3::from_axis_angle(&Vector3::y_axis(), b)
                * nalgebra::Rotation3::from_axis_angle(&Vector3::z_axis(), -g);
            if a * b != 0.0 {
                assert!((r - wrong.matrix()).abs().max() > 1e-3);
            }
            let (ra, pb) = Tilt::from_roll_pitch(a, b).roll_pitch();
            assert!((ra - a).abs() < 1e-15 && (pb - b).abs() < 1e-15);
        }
    }

    #[test]
    fn from_normal_inverts_normal() {
        for &(a, b) in &[(0.0, 0.0), (1e-9, -2e-9), (0.2, -0.1), (-0.34, 0.01)] {
            let t = Tilt {
                wx_rad: a,
                wy_rad: b,
            };
            let back = Tilt::from_normal(&t.normal());
            assert!((back.wx_rad - a).abs() < 1e-15 && (back.wy_rad - b).abs() < 1e-15);
        }
    }
}
