//! Geometric identification: Levenberg–Marquardt on the error model from measured poses.
//!
//! Residuals are the measured tip (mm) and axis (unit vector) minus the model's, each divided
//! by its measurement noise so both count by their information. The Jacobian is taken by
//! central differences through the model's forward kinematics. Some parameter combinations do
//! not change any tool pose (e.g. turning all platform joints and the spindle offsets
//! together); they are found from the singular values of the column-scaled Jacobian,
//! reported, and left at zero by a truncated (minimum-norm) step.

use nalgebra::{DMatrix, DVector};

use super::measurements::Measurement;
use super::model::{is_angle, parameter_name, ErrorModel, PARAMETER_COUNT};
use super::CalibError;
use crate::geometry::Geometry;

/// Options of the identification.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct IdentifyOptions {
    /// Tip measurement noise σ, mm.
    pub sigma_tip_mm: f64,
    /// Axis measurement noise σ, rad.
    pub sigma_axis_rad: f64,
    /// Singular values below this fraction of the largest are unidentifiable directions.
    pub rank_tolerance: f64,
    pub max_iterations: usize,
}

impl Default for IdentifyOptions {
    fn default() -> Self {
        IdentifyOptions {
            sigma_tip_mm: 1e-3,
            sigma_axis_rad: (1.0f64 / 3600.0).to_radians(),
            rank_tolerance: 1e-7,
            max_iterations: 50,
        }
    }
}

/// The result of identification.
#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
pub struct Identification {
    pub params: Vec<f64>,
    /// Identifiable directions (rank of the Jacobian).
    pub rank: usize,
    /// Parameters the measurements cannot (fully) see, with the fraction they do see.
    pub unidentifiable: Vec<String>,
    pub iterations: usize,
    /// RMS of the tip and axis residuals at the answer, mm and rad.
    pub rms_tip_mm: f64,
    pub rms_axis_rad: f64,
}

fn residuals(
    model: &ErrorModel,
    data: &[Measurement],
    opts: &IdentifyOptions,
    phis: &mut [[f64; 3]],
) -> Result<DVector<f64>, CalibError> {
    let mut r = DVector::zeros(6 * data.len());
    for (k, m) in data.iter().enumerate() {
        let t = model
            .forward(m.legs_mm, &mut phis[k])
            .map_err(|source| CalibError::Model {
                line: m.line,
                source,
            })?;
        for c in 0..3 {
            r[6 * k + c] = (t.tip_mm[c] - m.tip_mm[c]) / opts.sigma_tip_mm;
            r[6 * k + 3 + c] = (t.axis[c] - m.axis[c]) / opts.sigma_axis_rad;
        }
    }
    Ok(r)
}

fn jacobian(
    geom: &Geometry,
    params: &[f64; PARAMETER_COUNT],
    data: &[Measurement],
    opts: &IdentifyOptions,
    phis: &[[f64; 3]],
) -> Result<DMatrix<f64>, CalibError> {
    let mut j = DMatrix::zeros(6 * data.len(), PARAMETER_COUNT);
    for p in 0..PARAMETER_COUNT {
        let h = if is_angle(p) { 1e-6 } else { 1e-4 };
        let mut plus = *params;
        plus[p] += h;
        let mut minus = *params;
        minus[p] -= h;
        let mut ph = phis.to_vec();
        let rp = residuals(&ErrorModel::new(geom, plus), data, opts, &mut ph)?;
        let mut ph = phis.to_vec();
        let rm = residuals(&ErrorModel::new(geom, minus), data, opts, &mut ph)?;
        j.set_column(p, &((rp - rm) / (2.0 * h)));
    }
    Ok(j)
}

/// Identify the error parameters from measurements.
pub fn identify(
    geom: &Geometry,
    data: &[Measurement],
    opts: &IdentifyOptions,
) -> Result<Identification, CalibError> {
    if data.len() < 4 {
        return Err(CalibError::TooFewMeasurements {
            have: data.len(),
            need: 4,
        });
    }
    let mut params = [0.0; PARAMETER_COUNT];
    // A sphere centre off the leg axis only lengthens the leg to √(L² + e²): its first
    // derivative is zero at e = 0, so start it off zero (its sign is not observable).
    for chain in 0..3 {
        params[chain * super::model::PER_CHAIN + 6] = 0.1;
    }
    let mut phis = vec![[0.0; 3]; data.len()];
    let mut r = residuals(&ErrorModel::new(geom, params), data, opts, &mut phis)?;
    let mut cost = r.norm_squared();
    let mut lambda = 1e-3;
    let mut iterations = 0;
    let mut rank = 0;
    let mut null_space: Vec<DVector<f64>> = Vec::new();
    for it in 0..opts.max_iterations {
        iterations = it + 1;
        let j = jacobian(geom, &params, data, opts, &phis)?;
        // Column scaling so the rank test does not depend on mm versus rad.
        let norms: Vec<f64> = (0..PARAMETER_COUNT).map(|c| j.column(c).norm()).collect();
        let largest = norms.iter().copied().fold(0.0, f64::max);
        // A parameter that moves nothing keeps a unit scale (its column is zero either way).
        let scale: Vec<f64> = norms
            .iter()
            .map(|&n| if n > 1e-8 * largest { n } else { 1.0 })
            .collect();

        let mut js = j.clone();
        for (c, s) in scale.iter().enumerate() {
            js.column_mut(c).scale_mut(1.0 / s);
        }
        let svd = js.svd(true, true);
        let (u, vt) = (svd.u.as_ref().unwrap(), svd.v_t.as_ref().unwrap());
        let s_max = svd.singular_values.max();

        let g = u.transpose() * &r;
        let mut improved = false;
        for _ in 0..10 {
            let mut step = DVector::zeros(PARAMETER_COUNT);
            rank = 0;
            for (k, &s) in svd.singular_values.iter().enumerate() {
                if s > opts.rank_tolerance * s_max {
                    rank += 1;
                    let coef = -s * g[k] / (s * s + lambda * s_max * s_max);
                    step += vt.row(k).transpose() * coef;
                }
            }
            let mut trial = params;
            for c in 0..PARAMETER_COUNT {
                trial[c] += step[c] / scale[c];
            }
            let mut trial_phis = phis.clone();
            if let Ok(rt) = residuals(&ErrorModel::new(geom, trial), data, opts, &mut trial_phis) {
                let trial_cost = rt.norm_squared();
                if trial_cost < cost {
                    let relative = (cost - trial_cost) / cost.max(1e-300);
                    params = trial;
                    phis = trial_phis;
                    r = rt;
                    cost = trial_cost;
                    lambda = (lambda * 0.1).max(1e-12);
                    improved = relative > 1e-12;
                    break;
                }
            }
            lambda *= 10.0;
        }
        null_space = svd
            .singular_values
            .iter()
            .enumerate()
            .filter(|(_, &s)| s <= opts.rank_tolerance * s_max)
            .map(|(k, _)| vt.row(k).transpose())
            .collect();
        if !improved {
            break;
        }
    }
    // How much of each parameter the measurements see: 1 − its squared projection on the
    // unseen directions (in column-scaled coordinates).
    let unidentifiable = (0..PARAMETER_COUNT)
        .filter_map(|k| {
            let unseen: f64 = null_space.iter().map(|v| v[k] * v[k]).sum();
            (unseen > 0.01).then(|| {
                format!(
                    "{} (identifiable fraction {:.2})",
                    parameter_name(k),
                    (1.0 - unseen).max(0.0)
                )
            })
        })
        .collect();
    let n = data.len() as f64;
    let mut tip_sq = 0.0;
    let mut axis_sq = 0.0;
    for k in 0..data.len() {
        for c in 0..3 {
            tip_sq += (r[6 * k + c] * opts.sigma_tip_mm).powi(2);
            axis_sq += (r[6 * k + 3 + c] * opts.sigma_axis_rad).powi(2);
        }
    }
    Ok(Identification {
        params: params.to_vec(),
        rank,
        unidentifiable,
        iterations,
        rms_tip_mm: (tip_sq / n).sqrt(),
        rms_axis_rad: (axis_sq / n).sqrt(),
    })
}

/// Candidate poses for measurement: a grid over the seed's work range (tool-tip Z 156–356 mm,
/// θ1 every 30°, θ2 ±10°, ±20°, and flat).
fn candidate_legs(geom: &Geometry) -> Vec<[f64; 3]> {
    let mut out = Vec::new();
    for zi in 0..5 {
        let z = 156.0 + 50.0 * zi as f64;
        out.push(geom.inverse_tool(&crate::kinematics::ToolTarget {
            tip_mm: nalgebra::Vector3::new(0.0, 0.0, z),
            axis: nalgebra::Vector3::z(),
        }));
        for t1 in 0..6 {
            for t2 in [-20.0f64, -10.0, 10.0, 20.0] {
                let axis = crate::pose::Tilt::from_theta(
                    (30.0 * t1 as f64 + 15.0).to_radians(),
                    t2.to_radians(),
                )
                .normal();
                out.push(geom.inverse_tool(&crate::kinematics::ToolTarget {
                    tip_mm: nalgebra::Vector3::new(0.0, 0.0, z),
                    axis,
                }));
            }
        }
    }
    out.into_iter()
        .filter_map(|s| s.ok().map(|s| s.ik.legs_mm))
        .collect()
}

/// A measurement plan: `n` poses (as commanded legs) chosen greedily from a grid over the work
/// range to maximise det of the information matrix of the identification (D-optimal), so that
/// every identifiable parameter combination is seen from far apart poses.
pub fn measurement_plan(
    geom: &Geometry,
    n: usize,
    opts: &IdentifyOptions,
) -> Result<Vec<[f64; 3]>, CalibError> {
    let candidates = candidate_legs(geom);
    let nominal = [0.0; PARAMETER_COUNT];
    // Each candidate's Jacobian block (6 × P), as a pseudo-measurement at the nominal pose.
    let mut blocks = Vec::with_capacity(candidates.len());
    let mut phi = [0.0; 3];
    for (k, legs) in candidates.iter().enumerate() {
        let t = ErrorModel::new(geom, nominal)
            .forward(*legs, &mut phi)
            .map_err(|source| CalibError::Model { line: k, source })?;
        let m = Measurement {
            line: k,
            legs_mm: *legs,
            tip_mm: t.tip_mm,
            axis: t.axis,
        };
        blocks.push(jacobian(geom, &nominal, &[m], opts, &[phi])?);
    }
    // Column scales from all candidates together, and a small ridge for the null space.
    let mut scale = vec![0.0; PARAMETER_COUNT];
    for b in &blocks {
        for (c, s) in scale.iter_mut().enumerate() {
            *s += b.column(c).norm_squared();
        }
    }
    let scale: Vec<f64> = scale.iter().map(|s| s.sqrt().max(1e-12)).collect();
    let scaled: Vec<DMatrix<f64>> = blocks
        .iter()
        .map(|b| {
            let mut b = b.clone();
            for (c, s) in scale.iter().enumerate() {
                b.column_mut(c).scale_mut(1.0 / s);
            }
            b
        })
        .collect();
    let ridge = DMatrix::<f64>::identity(PARAMETER_COUNT, PARAMETER_COUNT) * 1e-6;
    let log_det = |m: &DMatrix<f64>| -> f64 {
        match m.clone().cholesky() {
            Some(c) => c.l().diagonal().iter().map(|d| 2.0 * d.ln()).sum(),
            None => f64::NEG_INFINITY,
        }
    };
    let mut info = ridge.clone();
    let mut chosen: Vec<usize> = Vec::with_capacity(n);
    for _ in 0..n {
        let mut best = (f64::NEG_INFINITY, 0);
        for (c, b) in scaled.iter().enumerate() {
            let trial = &info + b.transpose() * b;
            let v = log_det(&trial);
            if v > best.0 {
                best = (v, c);
            }
        }
        info += scaled[best.1].transpose() * &scaled[best.1];
        chosen.push(best.1);
    }
    // Exchange: replace a chosen pose by a candidate while that raises the determinant.
    let total = |chosen: &[usize]| {
        let mut m = ridge.clone();
        for &c in chosen {
            m += scaled[c].transpose() * &scaled[c];
        }
        log_det(&m)
    };
    super::exchange(&mut chosen, scaled.len(), false, 3, total, |v, best| {
        v > best + 1e-9
    });
    Ok(chosen.iter().map(|&c| candidates[c]).collect())
}
