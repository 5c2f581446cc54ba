//! Inverse and forward kinematics of the 3-RPS + XY table (seed ch. 3, SPEC §5).
//!
//! Inverse: the tilt fixes the rotation R; each sphere centre C_i = R·p_i + (X_u, Y_u, Z) must
//! lie in its chain's plane (t_i·C_i = 0). Because the three plane normals t_i are 120° apart,
//! Σ t_i t_iᵀ = (3/2)·I in the xy plane, so the parasitic shift is the projection
//! (X_u, Y_u) = −(2/3)·Σ t_i (t_i·R p_i); for the seed's layout this is eq. 3.11/3.13. The third
//! condition Σ t_i·R p_i = 0 holds for every zero-torsion tilt: that is why the mechanism has
//! no torsion. Legs are L_i = |C_i − A_i|.
//!
//! Forward: each leg makes an angle φ_i with the vertical inside its plane, so
//! C_i = (R_in − L_i sin φ_i)·u_i + L_i cos φ_i·ẑ; Newton–Raphson on φ makes all platform sides
//! √3·R_out (seed eq. 3.25–3.36, with the side test corrected, SPEC §9). The pose follows from
//! the three points.

use nalgebra::{Matrix3, Vector3};

use crate::error::{finite, KinError};
use crate::geometry::Geometry;
use crate::pose::{Pose, Tilt, TiltScalars};

/// The inverse-kinematic solution of one pose.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct IkSolution {
    pub pose: Pose,
    /// L_i, mm.
    pub legs_mm: [f64; 3],
    /// Parasitic translation (X_u, Y_u) of the output point, mm.
    pub parasitic_xy_mm: [f64; 2],
    /// Sphere centres C_i in the base frame, mm.
    pub sphere_centres_mm: [Vector3<f64>; 3],
    /// Platform rotation.
    pub rotation: Matrix3<f64>,
}

/// Every joint of the URDF tree, in the URDF's conventions (SI units only at the edge).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct JointPositions {
    /// Hinge angle φ_i: the leg's tilt from vertical toward the centre, rad.
    pub hinge_rad: [f64; 3],
    /// Leg lengths L_i, mm.
    pub legs_mm: [f64; 3],
    /// Spherical joint of chain i as revolutes about x, y, z of the leg frame, rad.
    pub sphere_rad: [[f64; 3]; 3],
    /// Table X, Y, mm.
    pub table_mm: [f64; 2],
}

/// A tool-tip target: the tip in the workpiece (table) frame and the tool axis.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ToolTarget {
    /// Tool tip, workpiece frame, mm.
    pub tip_mm: Vector3<f64>,
    /// Unit tool axis pointing from the tip to the spindle (up).
    pub axis: Vector3<f64>,
}

/// The solution of a tool-tip target: platform solution plus table position.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ToolSolution {
    pub ik: IkSolution,
    /// Table (X, Y), mm: carries the workpiece so the tip lands on the target.
    pub table_mm: [f64; 2],
}

/// Internal: R·p_i and its derivatives with respect to w_x and w_y.
pub(crate) struct RotatedPoints {
    pub points: [Vector3<f64>; 3],
    pub d_wx: [Vector3<f64>; 3],
    pub d_wy: [Vector3<f64>; 3],
}

impl Geometry {
    /// R·p_i for a tilt, optionally with derivatives (written out: this is the hot path).
    pub(crate) fn rotated_points(&self, tilt: &Tilt, derivatives: bool) -> RotatedPoints {
        let (a, b) = (tilt.wx_rad, tilt.wy_rad);
        let k = TiltScalars::new(a * a + b * b);
        let (s, f) = (k.sin_c, k.one_minus_cos_c);
        let mut out = RotatedPoints {
            points: [Vector3::zeros(); 3],
            d_wx: [Vector3::zeros(); 3],
            d_wy: [Vector3::zeros(); 3],
        };
        for i in 0..3 {
            let p = &self.platform_points[i];
            let (px, py) = (p.x, p.y);
            let ux = -b * b * px + a * b * py;
            let uy = a * b * px - a * a * py;
            let uz = a * py - b * px;
            out.points[i] = Vector3::new(px + f * ux, py + f * uy, s * uz);
            if derivatives {
                let (fa, fb) = (k.d_one_minus_cos_c * a, k.d_one_minus_cos_c * b);
                let (sa, sb) = (k.d_sin_c * a, k.d_sin_c * b);
                out.d_wx[i] = Vector3::new(
                    fa * ux + f * (b * py),
                    fa * uy + f * (b * px - 2.0 * a * py),
                    sa * uz + s * py,
                );
                out.d_wy[i] = Vector3::new(
                    fb * ux + f * (-2.0 * b * px + a * py),
                    fb * uy + f * (a * px),
                    sb * uz - s * px,
                );
            }
        }
        out
    }

    /// The shift (X_u, Y_u) that puts the rotated points into their chain planes.
    pub(crate) fn plane_shift(&self, rotated: &[Vector3<f64>; 3]) -> Vector3<f64> {
        let mut shift = Vector3::zeros();
        for (t, r) in self.tangent.iter().zip(rotated) {
            shift -= t * t.dot(r);
        }
        shift * (2.0 / 3.0)
    }

    /// Leg lengths of a pose, no limit checks: the hot path for Jacobians and path error.
    #[inline]
    pub fn leg_lengths(&self, pose: &Pose) -> [f64; 3] {
        let r = self.rotated_points(&pose.tilt, false);
        let shift = self.plane_shift(&r.points);
        std::array::from_fn(|i| {
            let c = r.points[i] + Vector3::new(shift.x, shift.y, pose.z_mm);
            (c - self.base_points[i]).norm()
        })
    }

    /// Inverse kinematics of a platform pose, with the leg, swing and tilt limits checked.
    pub fn inverse(&self, pose: &Pose) -> Result<IkSolution, KinError> {
        finite("Z", pose.z_mm)?;
        finite("w_x", pose.tilt.wx_rad)?;
        finite("w_y", pose.tilt.wy_rad)?;
        self.check_tilt(&pose.tilt)?;
        let sol = self.inverse_unchecked(pose);
        self.check_legs(&sol.legs_mm)?;
        self.check_swing(&sol)?;
        Ok(sol)
    }

    /// Inverse kinematics without limit checks (for analysis beyond the work range).
    pub fn inverse_unchecked(&self, pose: &Pose) -> IkSolution {
        let r = self.rotated_points(&pose.tilt, false);
        let shift = self.plane_shift(&r.points);
        let offset = Vector3::new(shift.x, shift.y, pose.z_mm);
        let sphere_centres_mm = r.points.map(|p| p + offset);
        let legs_mm = std::array::from_fn(|i| (sphere_centres_mm[i] - self.base_points[i]).norm());
        IkSolution {
            pose: *pose,
            legs_mm,
            parasitic_xy_mm: [shift.x, shift.y],
            sphere_centres_mm,
            rotation: pose.tilt.rotation(),
        }
    }

    pub(crate) fn check_legs(&self, legs: &[f64; 3]) -> Result<(), KinError> {
        for (i, &l) in legs.iter().enumerate() {
            finite("leg length", l)?;
            if l < self.limits.leg_min_mm || l > self.limits.leg_max_mm {
                return Err(KinError::LegOutOfRange {
                    chain: i + 1,
                    length_mm: l,
                    min_mm: self.limits.leg_min_mm,
                    max_mm: self.limits.leg_max_mm,
                });
            }
        }
        Ok(())
    }

    /// Swing of each spherical joint: angle between leg axis and platform normal.
    pub fn swing_rad(&self, sol: &IkSolution) -> [f64; 3] {
        self.swing_of(&sol.rotation, &sol.sphere_centres_mm)
    }

    fn swing_of(&self, rotation: &Matrix3<f64>, sphere_centres_mm: &[Vector3<f64>; 3]) -> [f64; 3] {
        let n = rotation.column(2).into_owned();
        std::array::from_fn(|i| {
            let d = (sphere_centres_mm[i] - self.base_points[i]).normalize();
            d.dot(&n).clamp(-1.0, 1.0).acos()
        })
    }

    fn check_swing(&self, sol: &IkSolution) -> Result<(), KinError> {
        self.check_swing_of(&sol.rotation, &sol.sphere_centres_mm)
    }

    fn check_tilt(&self, tilt: &Tilt) -> Result<(), KinError> {
        let tilt = tilt.angle_rad();
        if tilt > self.limits.tilt_max_rad + 1e-12 {
            return Err(KinError::TiltLimit {
                tilt_deg: tilt.to_degrees(),
                max_deg: self.limits.tilt_max_rad.to_degrees(),
            });
        }
        Ok(())
    }

    fn check_swing_of(
        &self,
        rotation: &Matrix3<f64>,
        sphere_centres_mm: &[Vector3<f64>; 3],
    ) -> Result<(), KinError> {
        for (i, s) in self
            .swing_of(rotation, sphere_centres_mm)
            .into_iter()
            .enumerate()
        {
            if s > self.limits.swing_max_rad {
                return Err(KinError::SwingLimit {
                    chain: i + 1,
                    swing_deg: s.to_degrees(),
                    max_deg: self.limits.swing_max_rad.to_degrees(),
                });
            }
        }
        Ok(())
    }

    /// The output point P = (X_u, Y_u, Z) of a solution, base frame, mm.
    pub fn output_point(sol: &IkSolution) -> Vector3<f64> {
        Vector3::new(
            sol.parasitic_xy_mm[0],
            sol.parasitic_xy_mm[1],
            sol.pose.z_mm,
        )
    }

    /// The tool tip of a platform pose in the base frame (table at zero), mm.
    pub fn tool_tip_mm(&self, sol: &IkSolution) -> Vector3<f64> {
        Self::output_point(sol) - sol.rotation.column(2) * self.tool_length_mm
    }

    /// The platform pose that holds the tool along `target.axis` with its tip at the target's
    /// height, and the normalised axis; the target is checked (finite, unit axis pointing up).
    pub fn tool_pose(&self, target: &ToolTarget) -> Result<(Pose, Vector3<f64>), KinError> {
        let a = &target.axis;
        for (what, v) in [
            ("tip x", target.tip_mm.x),
            ("tip y", target.tip_mm.y),
            ("tip z", target.tip_mm.z),
            ("axis x", a.x),
            ("axis y", a.y),
            ("axis z", a.z),
        ] {
            finite(what, v)?;
        }
        let norm = a.norm();
        if (norm - 1.0).abs() > 1e-6 || a.z <= 0.0 {
            return Err(KinError::BadToolAxis {
                x: a.x,
                y: a.y,
                z: a.z,
                norm,
            });
        }
        let axis = a / norm;
        let pose = Pose {
            z_mm: target.tip_mm.z + self.tool_length_mm * axis.z,
            tilt: Tilt::from_normal(&axis),
        };
        Ok((pose, axis))
    }

    /// Tool-tip inverse kinematics: the platform tilts so its normal is the tool axis, stands
    /// at Z = T_z + l·a_z, and the table absorbs X_u, Y_u and places the workpiece:
    /// table = (X_u, Y_u) − l·(a_x, a_y) − (T_x, T_y).
    pub fn inverse_tool(&self, target: &ToolTarget) -> Result<ToolSolution, KinError> {
        let (pose, axis) = self.tool_pose(target)?;
        let l = self.tool_length_mm;
        // The table must bring the workpiece under the tool: table = (X_u, Y_u) − l·a − T with
        // |X_u|, |Y_u| below the platform radius whatever the pose. A target beyond that is
        // refused for what it is, before the legs are looked at.
        let reach = self.limits.table_max_mm + self.platform_radius_mm;
        for (k, (tip, a)) in [(target.tip_mm.x, axis.x), (target.tip_mm.y, axis.y)]
            .into_iter()
            .enumerate()
        {
            if (tip + l * a).abs() > reach {
                return Err(KinError::TipOutOfReach {
                    axis: ['X', 'Y'][k],
                    tip_mm: tip,
                    table_max_mm: self.limits.table_max_mm,
                    platform_radius_mm: self.platform_radius_mm,
                });
            }
        }
        let ik = self.inverse(&pose)?;
        let table_mm = [
            ik.parasitic_xy_mm[0] - l * axis.x - target.tip_mm.x,
            ik.parasitic_xy_mm[1] - l * axis.y - target.tip_mm.y,
        ];
        self.check_table(&table_mm)?;
        Ok(ToolSolution { ik, table_mm })
    }

    /// The table's travel (and a finite position) on both axes.
    pub(crate) fn check_table(&self, table_mm: &[f64; 2]) -> Result<(), KinError> {
        for (k, &t) in table_mm.iter().enumerate() {
            finite("table position", t)?;
            if t.abs() > self.limits.table_max_mm {
                return Err(KinError::TableLimit {
                    axis: ['X', 'Y'][k],
                    position_mm: t,
                    max_mm: self.limits.table_max_mm,
                });
            }
        }
        Ok(())
    }

    /// Every passive and active joint of the URDF tree for a solution and table position.
    pub fn joint_positions(&self, sol: &IkSolution, table_mm: [f64; 2]) -> JointPositions {
        let mut hinge_rad = [0.0; 3];
        let mut sphere_rad = [[0.0; 3]; 3];
        for i in 0..3 {
            let d = (sol.sphere_centres_mm[i] - self.base_points[i]) / sol.legs_mm[i];
            // d = −sin φ·u_i + cos φ·ẑ
            let phi = (-d.dot(&self.radial[i])).atan2(d.z);
            hinge_rad[i] = phi;
            // Leg frame: Rz(ψ_i)·Ry(−φ_i); spherical joint M = legᵀ·R = Rx(r)·Ry(p)·Rz(y).
            let leg =
                nalgebra::Rotation3::from_axis_angle(&Vector3::z_axis(), self.chain_angle_rad(i))
                    * nalgebra::Rotation3::from_axis_angle(&Vector3::y_axis(), -phi);
            let m = leg.matrix().transpose() * sol.rotation;
            let pitch = m[(0, 2)].clamp(-1.0, 1.0).asin();
            let roll = (-m[(1, 2)]).atan2(m[(2, 2)]);
            let yaw = (-m[(0, 1)]).atan2(m[(0, 0)]);
            sphere_rad[i] = [roll, pitch, yaw];
        }
        JointPositions {
            hinge_rad,
            legs_mm: sol.legs_mm,
            sphere_rad,
            table_mm,
        }
    }
}

/// The result of forward kinematics.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FkSolution {
    pub pose: Pose,
    /// Output point P in the base frame, mm (x, y are the parasitic X_u, Y_u).
    pub output_point_mm: Vector3<f64>,
    pub rotation: Matrix3<f64>,
    pub sphere_centres_mm: [Vector3<f64>; 3],
    /// Leg angles φ_i from vertical, rad.
    pub hinge_rad: [f64; 3],
    /// Newton iterations used.
    pub iterations: u32,
}

impl FkSolution {
    /// The tool tip this pose reaches in the base frame (table at zero), mm.
    pub fn tool_tip_mm(&self, geom: &Geometry) -> Vector3<f64> {
        self.output_point_mm - self.rotation.column(2) * geom.tool_length_mm
    }

    /// Largest |side − √3·R_out| at the answer, mm.
    pub fn side_residual_mm(&self, geom: &Geometry) -> f64 {
        side_residual(&self.sphere_centres_mm, geom)
    }

    /// How well the three points close on a zero-torsion platform: largest distance of P from
    /// the pose's own (X_u, Y_u), and of the rotation from the pose's tilt (× R_out), mm.
    /// Computed on demand: it is a check, not part of the answer.
    pub fn closure_residual_mm(&self, geom: &Geometry) -> f64 {
        let r = geom.rotated_points(&self.pose.tilt, false);
        let shift = geom.plane_shift(&r.points);
        let p = &self.output_point_mm;
        (shift.x - p.x)
            .abs()
            .max((shift.y - p.y).abs())
            .max((self.pose.tilt.rotation() - self.rotation).amax() * geom.platform_radius_mm)
    }
}

/// Forward kinematics with a warm start: keeps the last leg angles (no allocation per solve).
#[derive(Debug, Clone, Copy)]
pub struct ForwardSolver {
    phi: [f64; 3],
    warm: bool,
    /// Iteration cap.
    pub max_iterations: u32,
}

impl Default for ForwardSolver {
    fn default() -> Self {
        ForwardSolver {
            phi: [0.0; 3],
            warm: false,
            max_iterations: 40,
        }
    }
}

impl ForwardSolver {
    /// Forget the warm start (the next solve starts cold).
    pub fn reset(&mut self) {
        self.warm = false;
    }

    /// Solve forward kinematics for leg lengths `legs_mm`, checking the limits inverse
    /// kinematics checks: the legs' strokes, and a pose within the tilt and every spherical
    /// joint within its swing (legs inside their strokes can hold the platform where the
    /// joints cannot go; such a pose is refused, and is no warm start for the next).
    pub fn solve(&mut self, geom: &Geometry, legs_mm: [f64; 3]) -> Result<FkSolution, KinError> {
        geom.check_legs(&legs_mm)?;
        let fk = self.solve_unchecked(geom, legs_mm)?;
        let within = geom
            .check_tilt(&fk.pose.tilt)
            .and_then(|()| geom.check_swing_of(&fk.rotation, &fk.sphere_centres_mm));
        if let Err(e) = within {
            self.warm = false;
            return Err(e);
        }
        Ok(fk)
    }

    /// Solve forward kinematics without limit checks. A warm start that fails (Newton from a
    /// pose far from this one can leave its basin) is tried once more cold.
    pub fn solve_unchecked(
        &mut self,
        geom: &Geometry,
        legs_mm: [f64; 3],
    ) -> Result<FkSolution, KinError> {
        let was_warm = self.warm;
        match self.newton(geom, legs_mm) {
            Err(_) if was_warm => {
                self.warm = false;
                self.newton(geom, legs_mm)
            }
            result => result,
        }
    }

    fn newton(&mut self, geom: &Geometry, legs_mm: [f64; 3]) -> Result<FkSolution, KinError> {
        for &l in &legs_mm {
            finite("leg length", l)?;
        }
        let r_in = geom.base_radius_mm;
        let side_sq = 3.0 * geom.platform_radius_mm * geom.platform_radius_mm;
        if !self.warm {
            // Cold start: the horizontal platform that these legs would hold (seed eq. 3.35
            // uses the home height; this is its per-leg form).
            let dr = r_in - geom.platform_radius_mm;
            self.phi = legs_mm.map(|l| (dr / l).clamp(-1.0, 1.0).asin());
        }
        let mut phi = self.phi;
        let points = |phi: &[f64; 3]| -> ([Vector3<f64>; 3], [Vector3<f64>; 3]) {
            let mut c = [Vector3::zeros(); 3];
            let mut dc = [Vector3::zeros(); 3];
            for i in 0..3 {
                let (s, co) = phi[i].sin_cos();
                let l = legs_mm[i];
                let u = &geom.radial[i];
                c[i] = Vector3::new((r_in - l * s) * u.x, (r_in - l * s) * u.y, l * co);
                dc[i] = Vector3::new(-l * co * u.x, -l * co * u.y, -l * s);
            }
            (c, dc)
        };
        const PAIRS: [(usize, usize); 3] = [(0, 1), (1, 2), (2, 0)];
        let mut iterations = 0;
        let c = loop {
            if iterations >= self.max_iterations {
                self.warm = false;
                return Err(KinError::NotConverged {
                    iterations,
                    residual_mm: side_residual(&points(&phi).0, geom),
                });
            }
            let (c, dc) = points(&phi);
            let mut jac = Matrix3::zeros();
            let mut f = Vector3::zeros();
            for (row, &(i, j)) in PAIRS.iter().enumerate() {
                let e = c[i] - c[j];
                f[row] = e.norm_squared() - side_sq;
                jac[(row, i)] = 2.0 * e.dot(&dc[i]);
                jac[(row, j)] = -2.0 * e.dot(&dc[j]);
            }
            let step = jac.lu().solve(&f).ok_or(KinError::Singular {
                what: "forward-kinematics Newton matrix",
                condition: f64::INFINITY,
            })?;
            iterations += 1;
            let step_max = step.amax();
            if !step_max.is_finite() || step_max > 1.0 {
                self.warm = false;
                return Err(unreachable(iterations, &legs_mm));
            }
            for k in 0..3 {
                phi[k] -= step[k];
            }
            // Newton converges quadratically: after a step below 1e-9 rad the error left is
            // of order 1e-18 rad. The points move along their tangents by the last step (the
            // curvature term is L·δ²/2 < 1e-15 mm), which saves re-evaluating them.
            if step_max < 1e-9 {
                break std::array::from_fn(|i| c[i] - dc[i] * step[i]);
            }
        };
        if phi.iter().any(|p| p.abs() >= std::f64::consts::FRAC_PI_2) {
            self.warm = false;
            return Err(unreachable(iterations, &legs_mm));
        }
        // Pose from the three points: P is their centroid (Σ p_i = 0) and
        // Σ (C_i − P) p_iᵀ = R·(3/2)R_out²·diag(1, 1, 0).
        let p = (c[0] + c[1] + c[2]) / 3.0;
        let mut m = Matrix3::zeros();
        for (ci, pi) in c.iter().zip(&geom.platform_points) {
            m += (ci - p) * pi.transpose();
        }
        let scale = 1.5 * geom.platform_radius_mm * geom.platform_radius_mm;
        let ex = m.column(0) / scale;
        let ey = m.column(1) / scale;
        let ez = ex.cross(&ey);
        if ez.z <= 0.0 {
            self.warm = false;
            return Err(KinError::WrongAssembly { normal_z: ez.z });
        }
        let rotation = Matrix3::from_columns(&[ex, ey, ez]);
        let tilt = Tilt::from_normal(&ez);
        let pose = Pose { z_mm: p.z, tilt };
        self.phi = phi;
        self.warm = true;
        Ok(FkSolution {
            pose,
            output_point_mm: p,
            rotation,
            sphere_centres_mm: c,
            hinge_rad: phi,
            iterations,
        })
    }
}

fn unreachable(iterations: u32, legs_mm: &[f64; 3]) -> KinError {
    KinError::Unreachable {
        iterations,
        l1: legs_mm[0],
        l2: legs_mm[1],
        l3: legs_mm[2],
    }
}

fn side_residual(c: &[Vector3<f64>; 3], geom: &Geometry) -> f64 {
    let side = geom.platform_side_mm();
    [(0, 1), (1, 2), (2, 0)]
        .iter()
        .map(|&(i, j)| ((c[i] - c[j]).norm() - side).abs())
        .fold(0.0, f64::max)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn deg(d: f64) -> f64 {
        d.to_radians()
    }

    #[test]
    fn home_pose_has_the_seed_leg_length() {
        let g = Geometry::default();
        let sol = g.inverse(&Pose::from_theta(393.0, 0.0, 0.0)).unwrap();
        for l in sol.legs_mm {
            // √(393² + 14²) = 393.2493...; the seed prints 393.249.
            assert!((l - (393f64.powi(2) + 14f64.powi(2)).sqrt()).abs() < 1e-12);
            assert!((l - 393.249).abs() < 5e-4);
        }
    }

    #[test]
    fn parasitic_shift_matches_seed_closed_forms() {
        let g = Geometry::default();
        let r = g.platform_radius_mm;
        for &t1 in &[0.1, 0.5, 1.0, 2.0, 3.0] {
            for &t2 in &[-0.35, -0.1, 0.05, 0.2, 0.35] {
                let sol = g.inverse_unchecked(&Pose::from_theta(300.0, t1, t2));
                let (s1, c1) = f64::sin_cos(t1);
                let c2 = t2.cos();
                let xu = r * (c1 * s1 - c1 * s1 * c2); // eq. 3.11
                let yu = 0.5 * r * (1.0 - c2) * (2.0 * t1).cos(); // eq. 3.13
                assert!((sol.parasitic_xy_mm[0] - xu).abs() < 1e-12);
                assert!((sol.parasitic_xy_mm[1] - yu).abs() < 1e-12);
            }
        }
    }

    #[test]
    fn chain_plane_constraints_hold_over_the_work_range() {
        let g = Geometry::default();
        let mut worst: f64 = 0.0;
        for zi in 0..=10 {
            for t1i in 1..=36 {
                for t2i in -8..=8 {
                    let z = 256.0 + 20.0 * zi as f64;
                    let pose = Pose::from_theta(z, deg(5.0 * t1i as f64), deg(2.5 * t2i as f64));
                    let sol = g.inverse_unchecked(&pose);
                    for i in 0..3 {
                        worst = worst.max(g.tangent[i].dot(&sol.sphere_centres_mm[i]).abs());
                    }
                    // and the platform is rigid: all sides √3·R_out
                    assert!(side_residual(&sol.sphere_centres_mm, &g) < 1e-10);
                }
            }
        }
        assert!(worst < 1e-9, "plane residual {worst:e} mm");
    }

    #[test]
    fn seed_printed_yaw_sign_breaks_the_chain_planes() {
        // SPEC §9: with γ_u = +atan(...) the sphere centres leave their planes by tens of mm.
        let g = Geometry::default();
        let (a, b) = (deg(20.0), deg(20.0));
        let wrong = nalgebra::Rotation3::from_axis_angle(&Vector3::x_axis(), a)
            * nalgebra::Rotation3::from_axis_angle(&Vector3::y_axis(), b)
            * nalgebra::Rotation3::from_axis_angle(&Vector3::z_axis(), -Tilt::parasitic_yaw(a, b));
        let rotated = g.platform_points.map(|p| wrong * p);
        // Two planes fix (X_u, Y_u); the third is then missed.
        let xu = -rotated[0].x;
        let yu = -(g.tangent[1].dot(&rotated[1]) + g.tangent[1].x * xu) / g.tangent[1].y;
        let miss = g.tangent[2]
            .dot(&(rotated[2] + Vector3::new(xu, yu, 0.0)))
            .abs();
        assert!(miss > 5.0, "miss {miss} mm");
    }

    #[test]
    fn fk_inverts_ik_over_a_dense_grid() {
        let g = Geometry::default();
        let mut fk = ForwardSolver::default();
        let (mut worst_z, mut worst_w, mut worst_p): (f64, f64, f64) = (0.0, 0.0, 0.0);
        let mut max_iter = 0;
        for zi in 0..=20 {
            // tool tip Z 156–356 → output point Z = tip + l·cos θ2
            let tip_z = 156.0 + 10.0 * zi as f64;
            for t1i in 1..=36 {
                for t2i in -20..=20 {
                    let t2 = deg(t2i as f64);
                    let pose =
                        Pose::from_theta(tip_z + 100.0 * t2.cos(), deg(5.0 * t1i as f64), t2);
                    let ik = g.inverse(&pose).unwrap();
                    for cold in [false, true] {
                        if cold {
                            fk.reset();
                        }
                        let sol = fk.solve(&g, ik.legs_mm).unwrap();
                        max_iter = max_iter.max(sol.iterations);
                        worst_z = worst_z.max((sol.pose.z_mm - pose.z_mm).abs());
                        worst_w = worst_w
                            .max((sol.pose.tilt.wx_rad - pose.tilt.wx_rad).abs())
                            .max((sol.pose.tilt.wy_rad - pose.tilt.wy_rad).abs());
                        let p = Geometry::output_point(&ik);
                        worst_p = worst_p.max((sol.output_point_mm - p).amax());
                        assert!(sol.closure_residual_mm(&g) < 1e-9);
                        assert!(sol.side_residual_mm(&g) < 1e-9);
                        if t2i != 0 {
                            let (a1, a2) = sol.pose.tilt.theta();
                            let (b1, b2) = pose.tilt.theta();
                            // θ1 = 0 and θ1 = 180° with θ2 negated are the same tilt.
                            let (d1, d2) = if (a1 - b1).abs() > 1.0 {
                                ((a1 - b1).abs() - std::f64::consts::PI, a2 + b2)
                            } else {
                                (a1 - b1, a2 - b2)
                            };
                            assert!(d1.abs() < 1e-9 && d2.abs() < 1e-9, "{d1:e} {d2:e}");
                        }
                    }
                }
            }
        }
        assert!(worst_z < 1e-9, "Z {worst_z:e} mm");
        assert!(worst_p < 1e-9, "P {worst_p:e} mm");
        assert!(worst_w < 1e-9, "w {worst_w:e} rad");
        assert!(max_iter <= 8, "iterations {max_iter}");
    }

    /// Legs inside their strokes that hold the platform where its joints cannot go are
    /// refused as IK would refuse that pose (FK answered them: a 67.8° swing, a 47.4° tilt),
    /// and such an answer leaves no warm start behind: the in-range pose after it solves (it
    /// was "unreachable" at the first iteration, from the far warm start).
    #[test]
    fn fk_refuses_poses_beyond_the_joints_and_recovers_after_them() {
        let g = Geometry::default();
        let mut fk = ForwardSolver::default();
        for legs in [[150.0, 520.0, 260.0], [525.718, 154.655, 300.467]] {
            let raw = ForwardSolver::default().solve_unchecked(&g, legs).unwrap();
            let swing = g.swing_of(&raw.rotation, &raw.sphere_centres_mm);
            assert!(
                raw.pose.tilt.angle_rad() > g.limits.tilt_max_rad
                    || swing.iter().any(|s| *s > g.limits.swing_max_rad),
                "{legs:?}: within the joints: the test shows nothing"
            );
            let err = fk.solve(&g, legs).unwrap_err();
            assert!(
                matches!(
                    err,
                    KinError::TiltLimit { .. } | KinError::SwingLimit { .. }
                ),
                "{legs:?}: {err:?}"
            );
            assert!(!fk.warm, "{legs:?}: a refused pose is no warm start");
        }
        // Unchecked, the far pose is the warm start; the next solve is near-flat.
        let mut fk = ForwardSolver::default();
        fk.solve_unchecked(&g, [525.718, 154.655, 300.467]).unwrap();
        let near = fk.solve_unchecked(&g, [343.053, 340.436, 340.203]).unwrap();
        let cold = ForwardSolver::default()
            .solve_unchecked(&g, [343.053, 340.436, 340.203])
            .unwrap();
        assert!((near.output_point_mm - cold.output_point_mm).norm() < 1e-9);
    }

    #[test]
    fn fk_rejects_bad_legs() {
        let g = Geometry::default();
        let mut fk = ForwardSolver::default();
        assert!(matches!(
            fk.solve(&g, [100.0, 393.0, 393.0]),
            Err(KinError::LegOutOfRange { chain: 1, .. })
        ));
        assert!(matches!(
            fk.solve(&g, [f64::NAN, 393.0, 393.0]),
            Err(KinError::NotFinite { .. })
        ));
        // Legs that cannot hold a platform of side √3·R_out.
        let err = fk.solve(&g, [140.0, 570.0, 570.0]).unwrap_err();
        assert!(
            matches!(
                err,
                KinError::Unreachable { .. }
                    | KinError::NotConverged { .. }
                    | KinError::WrongAssembly { .. }
            ),
            "{err:?}"
        );
        // and the solver recovers cold afterwards
        let ok = fk.solve(&g, [393.249, 393.249, 393.249]).unwrap();
        assert!((ok.pose.z_mm - 393.0).abs() < 1e-3);
    }

    #[test]
    fn ik_rejects_out_of_range_poses() {
        let g = Geometry::default();
        assert!(matches!(
            g.inverse(&Pose::from_theta(393.0, 0.3, deg(25.0))),
            Err(KinError::TiltLimit { .. })
        ));
        assert!(matches!(
            g.inverse(&Pose::from_theta(700.0, 0.3, deg(5.0))),
            Err(KinError::LegOutOfRange { .. })
        ));
        assert!(matches!(
            g.inverse(&Pose::from_theta(f64::INFINITY, 0.3, deg(5.0))),
            Err(KinError::NotFinite { .. })
        ));
    }

    #[test]
    fn tool_target_puts_the_tip_on_the_workpiece_point() {
        let g = Geometry::default();
        let axis = Vector3::new(0.1, -0.2, 1.0).normalize();
        let target = ToolTarget {
            tip_mm: Vector3::new(12.0, -30.0, 250.0),
            axis,
        };
        let sol = g.inverse_tool(&target).unwrap();
        // world tip = P − l·n; workpiece point = world − table
        let tip_world = g.tool_tip_mm(&sol.ik);
        let tip_work = tip_world - Vector3::new(sol.table_mm[0], sol.table_mm[1], 0.0);
        assert!((tip_work - target.tip_mm).amax() < 1e-12);
        assert!((sol.ik.rotation.column(2) - axis).amax() < 1e-15);
        // downward axis is refused
        let bad = ToolTarget {
            tip_mm: target.tip_mm,
            axis: -axis,
        };
        assert!(matches!(
            g.inverse_tool(&bad),
            Err(KinError::BadToolAxis { .. })
        ));
        let far = ToolTarget {
            tip_mm: Vector3::new(200.0, 0.0, 250.0),
            axis: Vector3::z(),
        };
        assert!(matches!(
            g.inverse_tool(&far),
            Err(KinError::TableLimit { axis: 'X', .. })
        ));
        // Far beyond any table position, with a height the legs cannot reach either: the
        // reach is what is wrong first, not a leg length.
        let beyond = ToolTarget {
            tip_mm: Vector3::new(1e9, 0.0, 0.0),
            axis: Vector3::z(),
        };
        let err = g.inverse_tool(&beyond).unwrap_err();
        assert!(
            matches!(err, KinError::TipOutOfReach { axis: 'X', tip_mm, .. } if tip_mm == 1e9),
            "{err}"
        );
        assert!(err
            .to_string()
            .starts_with("tool tip X = 1000000000 mm is out of reach"));
    }

    #[test]
    fn joint_positions_rebuild_the_legs_and_platform() {
        let g = Geometry::default();
        let sol = g
            .inverse(&Pose::from_theta(380.0, deg(40.0), deg(12.0)))
            .unwrap();
        let j = g.joint_positions(&sol, [0.0, 0.0]);
        for i in 0..3 {
            let leg =
                nalgebra::Rotation3::from_axis_angle(&Vector3::z_axis(), g.chain_angle_rad(i))
                    * nalgebra::Rotation3::from_axis_angle(&Vector3::y_axis(), -j.hinge_rad[i]);
            let c = g.base_points[i] + leg * Vector3::new(0.0, 0.0, j.legs_mm[i]);
            assert!((c - sol.sphere_centres_mm[i]).amax() < 1e-12);
            let [r, p, y] = j.sphere_rad[i];
            let ball = leg
                * nalgebra::Rotation3::from_axis_angle(&Vector3::x_axis(), r)
                * nalgebra::Rotation3::from_axis_angle(&Vector3::y_axis(), p)
                * nalgebra::Rotation3::from_axis_angle(&Vector3::z_axis(), y);
            assert!((ball.matrix() - sol.rotation).amax() < 1e-14);
        }
    }

    #[test]
    fn leg_limits_cover_the_seed_work_range() {
        let g = Geometry::default();
        let (mut lo, mut hi, mut swing, mut hinge) = (f64::MAX, f64::MIN, 0.0f64, 0.0f64);
        for zi in 0..=20 {
            for t1i in 0..72 {
                for t2i in [-20, -10, 0, 10, 20] {
                    let t2 = deg(t2i as f64);
                    let pose = Pose::from_theta(
                        156.0 + 10.0 * zi as f64 + 100.0 * t2.cos(),
                        deg(5.0 * t1i as f64),
                        t2,
                    );
                    let sol = g.inverse_unchecked(&pose);
                    for l in sol.legs_mm {
                        lo = lo.min(l);
                        hi = hi.max(l);
                    }
                    swing = g.swing_rad(&sol).into_iter().fold(swing, f64::max);
                    let j = g.joint_positions(&sol, [0.0, 0.0]);
                    hinge = j.hinge_rad.iter().fold(hinge, |m, h| m.max(h.abs()));
                }
            }
        }
        assert!(
            lo > g.limits.leg_min_mm && hi < g.limits.leg_max_mm,
            "{lo}..{hi}"
        );
        assert!(swing < g.limits.swing_max_rad, "{}", swing.to_degrees());
        // The URDF gives the plate hinges the spherical joints' ±45° (the seed gives none).
        assert!(hinge < g.limits.swing_max_rad, "{}", hinge.to_degrees());
    }
}
