//! Jacobian and the seed's evaluation tools (eq. 2.1–2.43, 4.1–4.22).
//!
//! The legs are explicit functions of the pose, so ∂L/∂q is exact and cheap; the Jacobian
//! J = ∂q/∂L follows by the inverse-function theorem (eq. 4.3, 4.13). q = (Z, w_x, w_y) is the
//! tilt vector form, which is not singular at zero tilt; [`Jacobian::theta_form`] converts to
//! the seed's (Z, θ1, θ2), which is.

use nalgebra::{Matrix2, Matrix3, SymmetricEigen, Vector3};

use crate::error::KinError;
use crate::geometry::Geometry;
use crate::pose::Pose;

/// ∂L/∂q and J = ∂q/∂L at a pose, q = (Z [mm], w_x [rad], w_y [rad]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Jacobian {
    /// Rows: legs; columns: Z, w_x, w_y. Units mm/mm and mm/rad.
    pub legs_by_pose: Matrix3<f64>,
    /// Rows: Z, w_x, w_y; columns: legs.
    pub pose_by_legs: Matrix3<f64>,
}

/// Drive-force and drive-speed evaluation (seed eq. 2.1–2.16, Table 2.1).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct DriveEvaluation {
    /// G_T: largest leg force per newton of force along Z, N/N.
    pub force_per_force: f64,
    /// G_R: largest leg force per N·mm of moment about a horizontal axis, N/(N·mm).
    pub force_per_moment: f64,
    /// ω_T: largest leg speed per mm/s of Z speed, (mm/s)/(mm/s).
    pub speed_per_speed: f64,
    /// ω_R: largest leg speed per deg/s of tilt rate, (mm/s)/(deg/s).
    pub speed_per_rate: f64,
}

/// Largest output errors under unit loads through the legs' compliance (eq. 2.33–2.43).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct ComplianceEvaluation {
    /// mm per N of force.
    pub translation_per_force: f64,
    /// rad per N of force.
    pub rotation_per_force: f64,
    /// mm per N·mm of moment.
    pub translation_per_moment: f64,
    /// rad per N·mm of moment.
    pub rotation_per_moment: f64,
}

impl Geometry {
    /// ∂L/∂q and its inverse at `pose`.
    pub fn jacobian(&self, pose: &Pose) -> Result<Jacobian, KinError> {
        let r = self.rotated_points(&pose.tilt, true);
        let shift = self.plane_shift(&r.points);
        let d_shift_x = self.plane_shift(&r.d_wx);
        let d_shift_y = self.plane_shift(&r.d_wy);
        let mut legs_by_pose = Matrix3::zeros();
        for i in 0..3 {
            let c = r.points[i] + Vector3::new(shift.x, shift.y, pose.z_mm);
            let e = c - self.base_points[i];
            let l = e.norm();
            let dcx = r.d_wx[i] + Vector3::new(d_shift_x.x, d_shift_x.y, 0.0);
            let dcy = r.d_wy[i] + Vector3::new(d_shift_y.x, d_shift_y.y, 0.0);
            legs_by_pose[(i, 0)] = e.z / l;
            legs_by_pose[(i, 1)] = e.dot(&dcx) / l;
            legs_by_pose[(i, 2)] = e.dot(&dcy) / l;
        }
        let pose_by_legs = invert(&legs_by_pose, "∂L/∂(Z, w) is singular")?;
        Ok(Jacobian {
            legs_by_pose,
            pose_by_legs,
        })
    }

    /// The seed's input/output ratio at `pose` (eq. 4.14–4.22): the largest ΔZ² for a unit
    /// leg input, i.e. the largest eigenvalue of J_Z·J_Zᵀ with J_Z = ∂Z/∂L.
    pub fn io_ratio(&self, pose: &Pose) -> Result<f64, KinError> {
        let j = self.jacobian(pose)?;
        let jz = j.pose_by_legs.row(0).transpose();
        Ok(max_eigenvalue(&(jz * jz.transpose())))
    }

    /// Drive force and speed per unit output (eq. 2.10–2.16), maximised over load direction.
    pub fn drive_evaluation(&self, pose: &Pose) -> Result<DriveEvaluation, KinError> {
        let j = self.jacobian(pose)?;
        // Statics G = Jᵀ F with J = ∂q/∂L: leg i sees column i of J against the load.
        let mut g = DriveEvaluation {
            force_per_force: 0.0,
            force_per_moment: 0.0,
            speed_per_speed: 0.0,
            speed_per_rate: 0.0,
        };
        for i in 0..3 {
            let col = j.pose_by_legs.column(i);
            g.force_per_force = g.force_per_force.max(col[0].abs());
            g.force_per_moment = g.force_per_moment.max(col[1].hypot(col[2]));
            let row = j.legs_by_pose.row(i);
            g.speed_per_speed = g.speed_per_speed.max(row[0].abs());
            g.speed_per_rate = g
                .speed_per_rate
                .max(row[1].hypot(row[2]) * std::f64::consts::PI / 180.0);
        }
        Ok(g)
    }

    /// Compliance C = J·K⁻¹·Jᵀ for leg stiffnesses `stiffness_n_per_mm` and its largest
    /// errors under unit loads (eq. 2.33–2.43).
    pub fn compliance(
        &self,
        pose: &Pose,
        stiffness_n_per_mm: [f64; 3],
    ) -> Result<(Matrix3<f64>, ComplianceEvaluation), KinError> {
        for &k in &stiffness_n_per_mm {
            if !(k.is_finite() && k > 0.0) {
                return Err(KinError::NotFinite {
                    what: "leg stiffness (must be finite and positive)",
                    value: k,
                });
            }
        }
        let j = self.jacobian(pose)?.pose_by_legs;
        let k_inv = Matrix3::from_diagonal(&Vector3::from(stiffness_n_per_mm.map(|k| 1.0 / k)));
        let c = j * k_inv * j.transpose();
        // Blocks: translation = Z (row/col 0), rotation = (w_x, w_y) (rows/cols 1..3).
        let c_pf = c[(0, 0)];
        let c_rf = c.fixed_view::<2, 1>(1, 0).into_owned();
        let c_pm = c.fixed_view::<1, 2>(0, 1).into_owned();
        let c_rm: Matrix2<f64> = c.fixed_view::<2, 2>(1, 1).into_owned();
        let eval = ComplianceEvaluation {
            translation_per_force: c_pf.abs(),
            rotation_per_force: c_rf.norm(),
            translation_per_moment: c_pm.norm(),
            rotation_per_moment: SymmetricEigen::new(c_rm.transpose() * c_rm)
                .eigenvalues
                .max()
                .max(0.0)
                .sqrt(),
        };
        Ok((c, eval))
    }
}

impl Jacobian {
    /// ∂L/∂(Z, θ1, θ2): the seed's form (eq. 4.13), singular at θ2 = 0.
    pub fn legs_by_theta(&self, pose: &Pose) -> Matrix3<f64> {
        let (t1, t2) = pose.tilt.theta();
        let (s1, c1) = t1.sin_cos();
        // w = θ2·(cos θ1, sin θ1)
        let dq = Matrix3::new(1.0, 0.0, 0.0, 0.0, -t2 * s1, c1, 0.0, t2 * c1, s1);
        self.legs_by_pose * dq
    }

    /// J in the seed's form ∂(Z, θ1, θ2)/∂L; refused near θ2 = 0 where θ1 is undefined.
    pub fn theta_form(&self, pose: &Pose) -> Result<Matrix3<f64>, KinError> {
        invert(
            &self.legs_by_theta(pose),
            "(Z, θ1, θ2) is singular at θ2 = 0",
        )
    }
}

fn invert(m: &Matrix3<f64>, what: &'static str) -> Result<Matrix3<f64>, KinError> {
    let svd = m.svd(false, false);
    let (max, min) = (svd.singular_values.max(), svd.singular_values.min());
    let condition = if min > 0.0 { max / min } else { f64::INFINITY };
    if condition.is_nan() || condition >= 1e10 {
        return Err(KinError::Singular { what, condition });
    }
    m.try_inverse()
        .ok_or(KinError::Singular { what, condition })
}

fn max_eigenvalue(m: &Matrix3<f64>) -> f64 {
    SymmetricEigen::new(*m).eigenvalues.max()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kinematics::ForwardSolver;

    fn deg(d: f64) -> f64 {
        d.to_radians()
    }

    #[test]
    fn legs_by_pose_matches_central_differences() {
        let g = Geometry::default();
        for &(z, t1, t2) in &[(393.0, 0.3, 0.0), (300.0, 1.2, 0.3), (450.0, 2.8, -0.25)] {
            let pose = Pose::from_theta(z, t1, t2);
            let j = g.jacobian(&pose).unwrap();
            for k in 0..3 {
                let h = if k == 0 { 1e-4 } else { 1e-6 };
                let mut plus = pose;
                let mut minus = pose;
                match k {
                    0 => {
                        plus.z_mm += h;
                        minus.z_mm -= h;
                    }
                    1 => {
                        plus.tilt.wx_rad += h;
                        minus.tilt.wx_rad -= h;
                    }
                    _ => {
                        plus.tilt.wy_rad += h;
                        minus.tilt.wy_rad -= h;
                    }
                }
                let (lp, lm) = (g.leg_lengths(&plus), g.leg_lengths(&minus));
                for i in 0..3 {
                    let fd = (lp[i] - lm[i]) / (2.0 * h);
                    let tol = 1e-7 * fd.abs().max(1.0);
                    assert!(
                        (fd - j.legs_by_pose[(i, k)]).abs() < tol,
                        "{i},{k}: {fd} vs {}",
                        j.legs_by_pose[(i, k)]
                    );
                }
            }
        }
    }

    #[test]
    fn pose_by_legs_matches_finite_differences_of_fk() {
        let g = Geometry::default();
        let mut fk = ForwardSolver::default();
        let pose = Pose::from_theta(350.0, deg(70.0), deg(-12.0));
        let j = g.jacobian(&pose).unwrap();
        let legs = g.leg_lengths(&pose);
        let h = 1e-5;
        for k in 0..3 {
            let mut lp = legs;
            let mut lm = legs;
            lp[k] += h;
            lm[k] -= h;
            let p = fk.solve(&g, lp).unwrap().pose;
            let m = fk.solve(&g, lm).unwrap().pose;
            let fd = Vector3::new(
                (p.z_mm - m.z_mm) / (2.0 * h),
                (p.tilt.wx_rad - m.tilt.wx_rad) / (2.0 * h),
                (p.tilt.wy_rad - m.tilt.wy_rad) / (2.0 * h),
            );
            let col = j.pose_by_legs.column(k);
            assert!((fd - col).amax() < 1e-7, "{k}: {fd} vs {col}");
        }
    }

    #[test]
    fn theta_form_is_singular_only_at_zero_tilt() {
        let g = Geometry::default();
        let flat = Pose::from_theta(393.0, 0.5, 0.0);
        assert!(g.jacobian(&flat).is_ok());
        assert!(matches!(
            g.jacobian(&flat).unwrap().theta_form(&flat),
            Err(KinError::Singular { .. })
        ));
        let tilted = Pose::from_theta(393.0, 0.5, deg(10.0));
        let j = g.jacobian(&tilted).unwrap();
        let jt = j.theta_form(&tilted).unwrap();
        // finite differences of L in (Z, θ1, θ2)
        let h = 1e-6;
        let lp = g.leg_lengths(&Pose::from_theta(393.0, 0.5 + h, deg(10.0)));
        let lm = g.leg_lengths(&Pose::from_theta(393.0, 0.5 - h, deg(10.0)));
        let lt = j.legs_by_theta(&tilted);
        for i in 0..3 {
            assert!(((lp[i] - lm[i]) / (2.0 * h) - lt[(i, 1)]).abs() < 1e-6);
        }
        assert!((jt * lt - Matrix3::identity()).amax() < 1e-12);
    }

    #[test]
    fn drive_speeds_match_the_seed_table_2_1() {
        // Table 2.1 over Z 293–458 mm, θ1 0–180°, θ2 ±30°: ω_T = 1 and ω_R = 5.5152.
        let g = Geometry::default();
        let mut max = DriveEvaluation {
            force_per_force: 0.0,
            force_per_moment: 0.0,
            speed_per_speed: 0.0,
            speed_per_rate: 0.0,
        };
        for zi in 0..=11 {
            for t1i in 0..=36 {
                for t2i in -30..=30 {
                    let pose = Pose::from_theta(
                        293.0 + 15.0 * zi as f64,
                        deg(5.0 * t1i as f64),
                        deg(t2i as f64),
                    );
                    let e = g.drive_evaluation(&pose).unwrap();
                    max.force_per_force = max.force_per_force.max(e.force_per_force);
                    max.force_per_moment = max.force_per_moment.max(e.force_per_moment);
                    max.speed_per_speed = max.speed_per_speed.max(e.speed_per_speed);
                    max.speed_per_rate = max.speed_per_rate.max(e.speed_per_rate);
                }
            }
        }
        // Our maxima on this 5°/1° grid: G_T 0.5749, G_R 0.00420, ω_T 1.0000, ω_R 5.5232;
        // the seed prints 0.5599, 0.0041, 1, 5.5152 (its grid and load model are not given).
        assert!(
            (max.speed_per_speed - 1.0).abs() < 1e-6,
            "{}",
            max.speed_per_speed
        );
        assert!(
            (max.speed_per_rate / 5.5152 - 1.0).abs() < 2e-3,
            "{}",
            max.speed_per_rate
        );
        assert!(
            (max.force_per_force / 0.5599 - 1.0).abs() < 0.03,
            "{}",
            max.force_per_force
        );
        assert!(
            (max.force_per_moment / 0.0041 - 1.0).abs() < 0.03,
            "{}",
            max.force_per_moment
        );
    }

    #[test]
    fn compliance_is_symmetric_and_scales_with_stiffness() {
        let g = Geometry::default();
        let pose = Pose::from_theta(393.0, deg(30.0), deg(10.0));
        let (c1, e1) = g.compliance(&pose, [1e4; 3]).unwrap();
        let (c2, e2) = g.compliance(&pose, [2e4; 3]).unwrap();
        assert!((c1 - c1.transpose()).amax() < 1e-18);
        assert!((c1 - 2.0 * c2).amax() < 1e-18);
        assert!((e1.translation_per_force - 2.0 * e2.translation_per_force).abs() < 1e-15);
        // At home, a vertical force is shared by three near-vertical legs: ΔZ ≈ F/(3k·cos²φ).
        let home = Pose::from_theta(393.0, 0.0, 0.0);
        let (_, e) = g.compliance(&home, [1e4; 3]).unwrap();
        let cos_phi = 393.0 / (393f64.powi(2) + 14f64.powi(2)).sqrt();
        assert!((e.translation_per_force - 1.0 / (3e4 * cos_phi * cos_phi)).abs() < 1e-12);
        assert!(matches!(
            g.compliance(&home, [0.0, 1.0, 1.0]),
            Err(KinError::NotFinite { .. })
        ));
    }

    #[test]
    fn io_ratio_grows_with_tilt_as_in_fig_4_1() {
        let g = Geometry::default();
        let flat = g.io_ratio(&Pose::from_theta(393.0, 0.0, 0.0)).unwrap();
        let tilted = g
            .io_ratio(&Pose::from_theta(393.0, 0.0, deg(20.0)))
            .unwrap();
        // flat: ∂Z/∂L_i = 1/(3 cos φ) for each leg → ΔZ² = 3·(1/(3 cos φ))² = 1/(3 cos²φ)
        let cos_phi = 393.0 / (393f64.powi(2) + 14f64.powi(2)).sqrt();
        assert!((flat - 1.0 / (3.0 * cos_phi * cos_phi)).abs() < 1e-12);
        assert!(tilted > flat);
    }
}
