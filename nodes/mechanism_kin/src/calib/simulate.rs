//! Simulated imperfect machines and their measurements (the seed's RecurDyn study, ch. 5.4):
//! every parameter of the error model gets a uniform random error of the given size, and
//! measurements get Gaussian noise. Deterministic for a seed.

use nalgebra::Vector3;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};

use super::measurements::Measurement;
use super::model::{is_angle, parameter_name, ErrorModel, ToolPose, PARAMETER_COUNT};
use super::{CalibError, Calibration};
use crate::geometry::Geometry;
use crate::kinematics::ToolTarget;
use crate::pose::Tilt;

/// A simulated machine with its measurement noise.
pub struct Simulation {
    pub truth: ErrorModel,
    rng: ChaCha8Rng,
    noise_tip_mm: f64,
    noise_axis_rad: f64,
}

/// A random tool target in the seed's work range: tip Z 156–356 mm, θ1 ∈ (0°, 180°],
/// θ2 ∈ [−20°, 20°], tip over the table origin.
pub fn random_target(rng: &mut impl Rng, geom: &Geometry) -> ToolTarget {
    let z = rng.random_range(156.0..=356.0);
    let t1 = rng.random_range(0.0..std::f64::consts::PI);
    let t2 = rng.random_range(-geom.limits.tilt_max_rad..=geom.limits.tilt_max_rad);
    ToolTarget {
        tip_mm: Vector3::new(0.0, 0.0, z),
        axis: Tilt::from_theta(t1, t2).normal(),
    }
}

impl Simulation {
    /// A machine with errors uniform in ±`length_error_mm` and ±`angle_error_rad`.
    pub fn new(
        geom: &Geometry,
        seed: u64,
        length_error_mm: f64,
        angle_error_rad: f64,
        noise_tip_mm: f64,
        noise_axis_rad: f64,
    ) -> Result<Self, CalibError> {
        for (what, v) in [
            ("length error", length_error_mm),
            ("angle error", angle_error_rad),
            ("tip noise", noise_tip_mm),
            ("axis noise", noise_axis_rad),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                return Err(CalibError::Settings(format!(
                    "{what} must be finite and not negative, got {v}"
                )));
            }
        }
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let mut params = [0.0; PARAMETER_COUNT];
        for (k, p) in params.iter_mut().enumerate() {
            let size = if is_angle(k) {
                angle_error_rad
            } else {
                length_error_mm
            };
            *p = rng.random_range(-1.0..=1.0) * size;
        }
        Ok(Simulation {
            truth: ErrorModel::new(geom, params),
            rng,
            noise_tip_mm,
            noise_axis_rad,
        })
    }

    fn noisy(&mut self, t: ToolPose) -> (Vector3<f64>, Vector3<f64>) {
        // σ was checked finite and ≥ 0 in `new`, which is all Normal::new refuses.
        let tip = Normal::new(0.0, self.noise_tip_mm).expect("σ checked in new");
        let ang = Normal::new(0.0, self.noise_axis_rad).expect("σ checked in new");
        let rng = &mut self.rng;
        let tip_mm = t.tip_mm + Vector3::new(tip.sample(rng), tip.sample(rng), tip.sample(rng));
        let axis =
            (t.axis + Vector3::new(ang.sample(rng), ang.sample(rng), ang.sample(rng))).normalize();
        (tip_mm, axis)
    }

    /// Measure the machine at commanded legs.
    pub fn measure_legs(&mut self, legs: &[[f64; 3]]) -> Result<Vec<Measurement>, CalibError> {
        let mut out = Vec::with_capacity(legs.len());
        for (k, l) in legs.iter().enumerate() {
            let mut phi = [0.0; 3];
            let t = self
                .truth
                .forward(*l, &mut phi)
                .map_err(|source| CalibError::Model {
                    line: k + 2,
                    source,
                })?;
            let (tip_mm, axis) = self.noisy(t);
            out.push(Measurement {
                line: k + 2,
                legs_mm: *l,
                tip_mm,
                axis,
            });
        }
        Ok(out)
    }

    /// Measure `n` random poses of the work range, commanded by nominal inverse kinematics.
    pub fn measure(&mut self, geom: &Geometry, n: usize) -> Result<Vec<Measurement>, CalibError> {
        let mut legs = Vec::with_capacity(n);
        while legs.len() < n {
            let target = random_target(&mut self.rng, geom);
            if let Ok(s) = geom.inverse_tool(&target) {
                legs.push(s.ik.legs_mm);
            }
        }
        self.measure_legs(&legs)
    }

    /// The true parameters as JSON (name → value).
    pub fn truth_json(&self) -> String {
        let map: serde_json::Map<String, serde_json::Value> = (0..PARAMETER_COUNT)
            .map(|k| (parameter_name(k), serde_json::json!(self.truth.params[k])))
            .collect();
        serde_json::to_string_pretty(&map).expect("plain numbers")
    }
}

/// Pose errors of a (possibly calibrated) controller on a true machine.
#[derive(Debug, Clone, Copy, PartialEq, Default, serde::Serialize)]
pub struct ValidationErrors {
    pub max_tip_mm: f64,
    pub rms_tip_mm: f64,
    pub max_axis_rad: f64,
    pub rms_axis_rad: f64,
    /// Targets the controller refused (outside its fitted region).
    pub refused: usize,
}

/// Drive the true machine to `targets` with legs and table from `cal` (or nominal IK when
/// `None`) and measure how far the tool lands, in tip position and tool-axis angle.
pub fn validate(
    geom: &Geometry,
    truth: &ErrorModel,
    cal: Option<&Calibration>,
    targets: &[ToolTarget],
) -> ValidationErrors {
    validate_with(truth, targets, |target| match cal {
        Some(c) => c
            .corrected_inverse(geom, target)
            .map(|c| (c.legs_mm, c.table_mm)),
        None => geom
            .inverse_tool(target)
            .map(|s| (s.ik.legs_mm, s.table_mm))
            .map_err(CalibError::from),
    })
}

/// Like [`validate`] with any controller: `command` gives legs and table for a target.
pub fn validate_with(
    truth: &ErrorModel,
    targets: &[ToolTarget],
    command: impl Fn(&ToolTarget) -> Result<([f64; 3], [f64; 2]), CalibError>,
) -> ValidationErrors {
    let mut e = ValidationErrors::default();
    let (mut tip_sq, mut axis_sq, mut n) = (0.0, 0.0, 0usize);
    for target in targets {
        let Ok((legs, table)) = command(target) else {
            e.refused += 1;
            continue;
        };
        let mut phi = [0.0; 3];
        let Ok(actual) = truth.forward(legs, &mut phi) else {
            e.refused += 1;
            continue;
        };
        let tip = actual.tip_mm - Vector3::new(table[0], table[1], 0.0);
        let d = (tip - target.tip_mm).norm();
        let a = actual.axis.cross(&target.axis).norm().asin();
        e.max_tip_mm = e.max_tip_mm.max(d);
        e.max_axis_rad = e.max_axis_rad.max(a);
        tip_sq += d * d;
        axis_sq += a * a;
        n += 1;
    }
    if n > 0 {
        e.rms_tip_mm = (tip_sq / n as f64).sqrt();
        e.rms_axis_rad = (axis_sq / n as f64).sqrt();
    }
    e
}
