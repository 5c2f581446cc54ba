//! The geometric error model (seed ch. 5.4.1.2, Fig. 5.3): 38 parameters, all zero for the
//! nominal machine, used both to simulate an imperfect machine and to identify one.
//!
//! Per chain i, in its own frame (u_i radial, t_i tangent, ẑ up):
//! - `base_radial_mm`, `base_tangential_mm`, `base_z_mm`: position error of hinge A_i (S).
//! - `hinge_about_radial_rad`, `hinge_about_z_rad`: direction error of the hinge axis.
//! - `leg_offset_mm`: leg zero offset; the true leg is the commanded length plus this (BL).
//! - `sphere_normal_mm`: sphere centre off the leg axis, in the chain plane (CL).
//! - `sphere_axial_mm`: sphere centre off the chain plane, along the hinge axis (SL).
//! - `platform_radius_mm`, `platform_angle_rad`, `platform_z_mm`: position error of the
//!   sphere centre on the platform (RL).
//!
//! And for the spindle (platform frame): `output_x_mm`, `output_y_mm`, `output_z_mm`, the
//! output point (OP; z includes a tool-length error), and `spindle_about_x_rad`,
//! `spindle_about_y_rad`, the spindle direction (SP).

use nalgebra::{Matrix3, Rotation3, Vector3};

use crate::error::KinError;
use crate::geometry::Geometry;

pub const PER_CHAIN: usize = 11;
pub const PARAMETER_COUNT: usize = 3 * PER_CHAIN + 5;

const CHAIN_NAMES: [&str; PER_CHAIN] = [
    "base_radial_mm",
    "base_tangential_mm",
    "base_z_mm",
    "hinge_about_radial_rad",
    "hinge_about_z_rad",
    "leg_offset_mm",
    "sphere_normal_mm",
    "sphere_axial_mm",
    "platform_radius_mm",
    "platform_angle_rad",
    "platform_z_mm",
];
const TOOL_NAMES: [&str; 5] = [
    "output_x_mm",
    "output_y_mm",
    "output_z_mm",
    "spindle_about_x_rad",
    "spindle_about_y_rad",
];

/// Name of parameter k (`chain2_leg_offset_mm`, `output_z_mm`, …).
pub fn parameter_name(k: usize) -> String {
    if k < 3 * PER_CHAIN {
        format!("chain{}_{}", k / PER_CHAIN + 1, CHAIN_NAMES[k % PER_CHAIN])
    } else {
        TOOL_NAMES[k - 3 * PER_CHAIN].to_string()
    }
}

/// Whether parameter k is an angle (rad) rather than a length (mm).
pub fn is_angle(k: usize) -> bool {
    parameter_name(k).ends_with("_rad")
}

/// A machine: nominal geometry plus parameter errors, with the derived per-chain vectors.
#[derive(Debug, Clone)]
pub struct ErrorModel {
    pub params: [f64; PARAMETER_COUNT],
    base: [Vector3<f64>; 3],
    hinge: [Vector3<f64>; 3],
    /// In-plane basis: leg direction d(φ) = cos φ·e1 − sin φ·e2.
    e1: [Vector3<f64>; 3],
    e2: [Vector3<f64>; 3],
    platform: [Vector3<f64>; 3],
    /// Platform-frame triangle frame (for the rigid fit).
    platform_frame: Matrix3<f64>,
    output_point: Vector3<f64>,
    spindle: Vector3<f64>,
    tool_length_mm: f64,
    base_radius_mm: f64,
    platform_radius_mm: f64,
}

/// The tool as a machine places it: tip (base frame, table at zero) and axis.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ToolPose {
    pub tip_mm: Vector3<f64>,
    pub axis: Vector3<f64>,
}

fn triangle_frame(p: &[Vector3<f64>; 3]) -> Matrix3<f64> {
    let x = (p[1] - p[0]).normalize();
    let z = (p[1] - p[0]).cross(&(p[2] - p[0])).normalize();
    let y = z.cross(&x);
    Matrix3::from_columns(&[x, y, z])
}

impl ErrorModel {
    pub fn new(geom: &Geometry, params: [f64; PARAMETER_COUNT]) -> Self {
        let mut base = [Vector3::zeros(); 3];
        let mut hinge = [Vector3::zeros(); 3];
        let mut e1 = [Vector3::zeros(); 3];
        let mut e2 = [Vector3::zeros(); 3];
        let mut platform = [Vector3::zeros(); 3];
        for i in 0..3 {
            let p = &params[i * PER_CHAIN..(i + 1) * PER_CHAIN];
            let (u, t) = (geom.radial[i], geom.tangent[i]);
            base[i] = geom.base_points[i] + u * p[0] + t * p[1] + Vector3::z() * p[2];
            let h = Rotation3::from_axis_angle(&Vector3::z_axis(), p[4])
                * Rotation3::from_axis_angle(&nalgebra::Unit::new_normalize(u), p[3])
                * t;
            hinge[i] = h.normalize();
            e1[i] = (Vector3::z() - hinge[i] * hinge[i].z).normalize();
            e2[i] = hinge[i].cross(&e1[i]);
            let angle = geom.chain_angle_rad(i) + p[9];
            let r = geom.platform_radius_mm + p[8];
            platform[i] = Vector3::new(r * angle.cos(), r * angle.sin(), p[10]);
        }
        let q = &params[3 * PER_CHAIN..];
        let spindle = Rotation3::from_axis_angle(&Vector3::y_axis(), q[4])
            * Rotation3::from_axis_angle(&Vector3::x_axis(), q[3])
            * Vector3::z();
        ErrorModel {
            params,
            base,
            hinge,
            e1,
            e2,
            platform_frame: triangle_frame(&platform),
            platform,
            output_point: Vector3::new(q[0], q[1], q[2]),
            spindle,
            tool_length_mm: geom.tool_length_mm,
            base_radius_mm: geom.base_radius_mm,
            platform_radius_mm: geom.platform_radius_mm,
        }
    }

    /// The nominal machine.
    pub fn nominal(geom: &Geometry) -> Self {
        ErrorModel::new(geom, [0.0; PARAMETER_COUNT])
    }

    fn sphere(&self, i: usize, leg: f64, phi: f64) -> (Vector3<f64>, Vector3<f64>) {
        let (s, c) = phi.sin_cos();
        let d = self.e1[i] * c - self.e2[i] * s;
        let n = -self.e1[i] * s - self.e2[i] * c;
        let p = &self.params[i * PER_CHAIN..];
        let length = leg + p[5];
        let centre = self.base[i] + d * length + n * p[6] + self.hinge[i] * p[7];
        // ∂n/∂φ = −d
        let d_centre = n * length - d * p[6];
        (centre, d_centre)
    }

    /// Forward kinematics of this machine for commanded legs, warm-started from `phi`.
    pub fn forward(&self, legs_mm: [f64; 3], phi: &mut [f64; 3]) -> Result<ToolPose, KinError> {
        if phi.iter().all(|&p| p == 0.0) {
            let dr = self.base_radius_mm - self.platform_radius_mm;
            *phi = legs_mm.map(|l| (dr / l).clamp(-1.0, 1.0).asin());
        }
        const PAIRS: [(usize, usize); 3] = [(0, 1), (1, 2), (2, 0)];
        let sides: [f64; 3] =
            PAIRS.map(|(i, j)| (self.platform[i] - self.platform[j]).norm_squared());
        let mut converged = false;
        let mut iterations = 0;
        while iterations < 40 {
            let pts: [(Vector3<f64>, Vector3<f64>); 3] =
                std::array::from_fn(|i| self.sphere(i, legs_mm[i], phi[i]));
            let mut jac = Matrix3::zeros();
            let mut f = Vector3::zeros();
            for (row, &(i, j)) in PAIRS.iter().enumerate() {
                let e = pts[i].0 - pts[j].0;
                f[row] = e.norm_squared() - sides[row];
                jac[(row, i)] = 2.0 * e.dot(&pts[i].1);
                jac[(row, j)] = -2.0 * e.dot(&pts[j].1);
            }
            let step = jac.lu().solve(&f).ok_or(KinError::Singular {
                what: "error-model forward kinematics",
                condition: f64::INFINITY,
            })?;
            iterations += 1;
            if !step.amax().is_finite() || step.amax() > 1.0 {
                break;
            }
            for k in 0..3 {
                phi[k] -= step[k];
            }
            if step.amax() < 1e-13 {
                converged = true;
                break;
            }
        }
        if !converged {
            *phi = [0.0; 3];
            return Err(KinError::NotConverged {
                iterations,
                residual_mm: f64::NAN,
            });
        }
        let c: [Vector3<f64>; 3] = std::array::from_fn(|i| self.sphere(i, legs_mm[i], phi[i]).0);
        let rotation = triangle_frame(&c) * self.platform_frame.transpose();
        let origin = c[0] - rotation * self.platform[0];
        let axis = rotation * self.spindle;
        if axis.z <= 0.0 {
            *phi = [0.0; 3];
            return Err(KinError::WrongAssembly { normal_z: axis.z });
        }
        Ok(ToolPose {
            tip_mm: origin + rotation * self.output_point - axis * self.tool_length_mm,
            axis,
        })
    }

    /// Legs that make this machine put the tool tip at height `tip_z_mm` with axis `axis`
    /// (Newton from the nominal solution); returns the legs and the tip they reach.
    pub fn inverse(
        &self,
        geom: &Geometry,
        tip_z_mm: f64,
        axis: &Vector3<f64>,
    ) -> Result<([f64; 3], ToolPose), KinError> {
        let (pose, _) = geom.tool_pose(&crate::kinematics::ToolTarget {
            tip_mm: Vector3::new(0.0, 0.0, tip_z_mm),
            axis: *axis,
        })?;
        let mut legs = geom.inverse(&pose)?.legs_mm;
        let mut phi = [0.0; 3];
        let residual = |t: &ToolPose| {
            Vector3::new(t.tip_mm.z - tip_z_mm, t.axis.x - axis.x, t.axis.y - axis.y)
        };
        for _ in 0..20 {
            let now = self.forward(legs, &mut phi)?;
            let r = residual(&now);
            if r.x.abs() < 1e-11 && r.y.abs() < 1e-14 && r.z.abs() < 1e-14 {
                return Ok((legs, now));
            }
            let mut jac = Matrix3::zeros();
            let h = 1e-6;
            for k in 0..3 {
                let mut lp = legs;
                lp[k] += h;
                let mut ph = phi;
                let moved = self.forward(lp, &mut ph)?;
                jac.set_column(k, &((residual(&moved) - r) / h));
            }
            let step = jac.lu().solve(&r).ok_or(KinError::Singular {
                what: "calibrated inverse kinematics",
                condition: f64::INFINITY,
            })?;
            for k in 0..3 {
                legs[k] -= step[k];
            }
        }
        let now = self.forward(legs, &mut phi)?;
        Ok((legs, now))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pose::Pose;

    #[test]
    fn nominal_model_is_the_closed_form_machine() {
        let g = Geometry::default();
        let m = ErrorModel::nominal(&g);
        let mut phi = [0.0; 3];
        for &(z, t1, t2) in &[(393.0, 0.3, 0.1), (300.0, 2.0, -0.3), (450.0, 1.0, 0.0)] {
            let ik = g.inverse(&Pose::from_theta(z, t1, t2)).unwrap();
            let t = m.forward(ik.legs_mm, &mut phi).unwrap();
            assert!((t.tip_mm - g.tool_tip_mm(&ik)).amax() < 1e-10);
            assert!((t.axis - ik.rotation.column(2)).amax() < 1e-13);
        }
        assert_eq!(parameter_name(0), "chain1_base_radial_mm");
        assert_eq!(parameter_name(PARAMETER_COUNT - 1), "spindle_about_y_rad");
        assert!(is_angle(3) && !is_angle(5));
    }

    #[test]
    fn leg_offset_moves_like_a_longer_leg() {
        let g = Geometry::default();
        let mut p = [0.0; PARAMETER_COUNT];
        p[PER_CHAIN + 5] = 0.3; // chain 2 leg offset
        let m = ErrorModel::new(&g, p);
        let nominal = ErrorModel::nominal(&g);
        let legs = [380.0, 390.0, 400.0];
        let (mut a, mut b) = ([0.0; 3], [0.0; 3]);
        let t = m.forward(legs, &mut a).unwrap();
        let u = nominal.forward([380.0, 390.3, 400.0], &mut b).unwrap();
        assert!((t.tip_mm - u.tip_mm).amax() < 1e-10);
    }

    #[test]
    fn inverse_of_an_imperfect_machine_hits_its_target() {
        let g = Geometry::default();
        let mut p = [0.0; PARAMETER_COUNT];
        for (k, v) in p.iter_mut().enumerate() {
            *v = if is_angle(k) { 0.003 } else { 0.4 } * if k % 2 == 0 { 1.0 } else { -1.0 };
        }
        let m = ErrorModel::new(&g, p);
        let axis = Vector3::new(0.1, 0.05, 1.0).normalize();
        let (legs, reached) = m.inverse(&g, 230.0, &axis).unwrap();
        assert!((reached.tip_mm.z - 230.0).abs() < 1e-10);
        assert!((reached.axis - axis).amax() < 1e-13);
        let mut phi = [0.0; 3];
        let again = m.forward(legs, &mut phi).unwrap();
        assert!((again.tip_mm - reached.tip_mm).amax() < 1e-10);
    }
}
