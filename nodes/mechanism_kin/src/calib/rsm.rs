//! Response-surface calibration (seed ch. 5–6).
//!
//! Predictors are the commanded legs (L1, L2, L3), scaled to [−1, 1] over the design; the
//! responses are the measured tool tip (x, y, z) and tilt. The seed fits the tilt as (θ1, θ2);
//! those are polar coordinates of the tilt vector w = θ2·(cos θ1, sin θ1), and θ1 is so
//! nonlinear in the legs at small θ2 that a quadratic misses it by degrees (measured: 4.8° mean
//! leave-one-out error over θ1 10–60°, θ2 3–8°). We fit the tilt vector's components instead
//! (0.0009° and 0.0006° there): the same information without the polar singularity. Each response gets the full
//! quadratic (10 terms, eq. 6.1), fitted by least squares; terms whose t value is below
//! t(α/2, n−p) are dropped and the reduced model refitted; of the two, the one with the smaller
//! mean error (ME) is kept. The seed measures ME against its simulator's truth, which a real
//! user does not have: here ME is the leave-one-out prediction error, from the hat matrix.
//! Corrected legs solve the three surfaces Z, θ1, θ2 = target by Newton (eq. 6.4); the table
//! absorbs the x, y surfaces.
//!
//! A quadratic answers anywhere, but is only right near its data. A target is refused when
//! the legs it needs are farther from the measured legs than any measurement is from the
//! rest: its leverage `h(x) = t(x)ᵀ(XᵀX)⁻¹t(x)` (the prediction variance in units of σ²)
//! above the largest `h_ii` of the fit — the boundary of the data's ellipsoid, which finds
//! the hidden extrapolation a box around the data's poses does not (Montgomery, *Design and
//! Analysis of Experiments*, on regressor-variable hulls). Within it, an answer is given
//! only if its standard error — the surfaces' residual σ (what a quadratic misses of this
//! machine over the measured poses) times √(1 + h) — is within a tolerance (0.02 mm and
//! 0.005°, the seed's result): surfaces fitted over too wide a region answer nothing rather
//! than answer a few tenths of a millimetre off.

use nalgebra::{DMatrix, DVector, Matrix3, Vector3};
use statrs::distribution::{ContinuousCDF, StudentsT};

use super::measurements::Measurement;
use super::{CalibError, CorrectedCommand};
use crate::geometry::Geometry;
use crate::kinematics::ToolTarget;
use crate::pose::Tilt;

pub const TERMS: usize = 10;
pub const TERM_NAMES: [&str; TERMS] = [
    "1", "L1", "L2", "L3", "L1·L2", "L1·L3", "L2·L3", "L1²", "L2²", "L3²",
];
pub const RESPONSES: [&str; 5] = [
    "tip_x_mm",
    "tip_y_mm",
    "tip_z_mm",
    "tilt_x_deg",
    "tilt_y_deg",
];

/// The pose region a response surface is fitted over (tool-tip Z and tilt).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Region {
    pub tip_z_mm: [f64; 2],
    pub theta1_deg: [f64; 2],
    pub theta2_deg: [f64; 2],
}

impl Default for Region {
    /// Around the seed's ch. 6 example target (Z_s 200 mm, θ1 30°, θ2 5°).
    fn default() -> Self {
        Region {
            tip_z_mm: [175.0, 225.0],
            theta1_deg: [10.0, 60.0],
            theta2_deg: [3.0, 8.0],
        }
    }
}

fn terms(x: &Vector3<f64>) -> [f64; TERMS] {
    [
        1.0,
        x[0],
        x[1],
        x[2],
        x[0] * x[1],
        x[0] * x[2],
        x[1] * x[2],
        x[0] * x[0],
        x[1] * x[1],
        x[2] * x[2],
    ]
}

fn term_gradients(x: &Vector3<f64>) -> [[f64; 3]; TERMS] {
    [
        [0.0, 0.0, 0.0],
        [1.0, 0.0, 0.0],
        [0.0, 1.0, 0.0],
        [0.0, 0.0, 1.0],
        [x[1], x[0], 0.0],
        [x[2], 0.0, x[0]],
        [0.0, x[2], x[1]],
        [2.0 * x[0], 0.0, 0.0],
        [0.0, 2.0 * x[1], 0.0],
        [0.0, 0.0, 2.0 * x[2]],
    ]
}

/// One fitted response surface.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Surface {
    pub response: String,
    /// Kept term indices into [`TERM_NAMES`] and their coefficients.
    pub terms: Vec<usize>,
    pub coefficients: Vec<f64>,
    pub r2: f64,
    pub adjusted_r2: f64,
    /// Mean absolute leave-one-out error of the kept model.
    pub mean_error: f64,
    /// Residual standard deviation of the kept model (what the surface misses at its data).
    #[serde(default)]
    pub sigma: f64,
    /// Mean error of the other candidate (full if reduced was kept, reduced otherwise).
    pub other_mean_error: f64,
    /// Whether the t-test-reduced model was kept.
    pub reduced: bool,
}

impl Surface {
    fn value(&self, x: &Vector3<f64>) -> f64 {
        let t = terms(x);
        self.terms
            .iter()
            .zip(&self.coefficients)
            .map(|(&k, c)| c * t[k])
            .sum()
    }

    fn gradient(&self, x: &Vector3<f64>) -> Vector3<f64> {
        let g = term_gradients(x);
        let mut out = Vector3::zeros();
        for (&k, c) in self.terms.iter().zip(&self.coefficients) {
            out += Vector3::from(g[k]) * *c;
        }
        out
    }
}

struct Fit {
    coefficients: Vec<f64>,
    /// Residual standard deviation, √(SSE / (n − p)).
    sigma: f64,
    t_values: Vec<f64>,
    r2: f64,
    adjusted_r2: f64,
    loo_mean_error: f64,
}

fn fit(xs: &[Vector3<f64>], y: &DVector<f64>, kept: &[usize]) -> Result<Fit, CalibError> {
    let n = xs.len();
    let p = kept.len();
    if n <= p {
        return Err(CalibError::TooFewMeasurements {
            have: n,
            need: p + 1,
        });
    }
    let x = DMatrix::from_fn(n, p, |i, j| terms(&xs[i])[kept[j]]);
    let xtx = x.transpose() * &x;
    let xtx_inv = xtx.try_inverse().ok_or(CalibError::Rsm(
        "the design does not determine the quadratic (XᵀX singular): spread the poses".into(),
    ))?;
    let b = &xtx_inv * x.transpose() * y;
    let fitted = &x * &b;
    let resid = y - &fitted;
    let sse = resid.norm_squared();
    let mean = y.mean();
    let syy: f64 = y.iter().map(|v| (v - mean).powi(2)).sum();
    let dof = (n - p) as f64;
    let sigma2 = sse / dof;
    let t_values = (0..p)
        .map(|j| b[j] / (sigma2 * xtx_inv[(j, j)]).sqrt())
        .collect();
    let hat_diag: Vec<f64> = (0..n)
        .map(|i| {
            let row = x.row(i);
            (row * &xtx_inv * row.transpose())[(0, 0)]
        })
        .collect();
    let loo_mean_error = (0..n)
        .map(|i| (resid[i] / (1.0 - hat_diag[i]).max(1e-12)).abs())
        .sum::<f64>()
        / n as f64;
    let r2 = if syy > 0.0 { 1.0 - sse / syy } else { 1.0 };
    Ok(Fit {
        coefficients: b.iter().copied().collect(),
        sigma: sigma2.sqrt(),
        t_values,
        r2,
        adjusted_r2: 1.0 - (sse / dof) / (syy / (n as f64 - 1.0)).max(1e-300),
        loo_mean_error,
    })
}

/// Fitted surfaces with the predictor scaling and region.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ResponseSurfaces {
    pub leg_centre_mm: [f64; 3],
    pub leg_half_range_mm: [f64; 3],
    /// tip x, tip y, tip z, θ1, θ2.
    pub surfaces: Vec<Surface>,
    /// The region of the measurements (target poses outside it are refused).
    pub region: Region,
    pub significance: f64,
    /// θ1 is unwrapped to within 180° of this direction, deg.
    pub theta1_reference_deg: f64,
    /// Where the data is (files written before it existed: the box `region` only).
    #[serde(default)]
    pub leverage: Option<LeverageLimit>,
}

impl ResponseSurfaces {
    /// What a file must hold for [`ResponseSurfaces::solve`] to use it: one surface per
    /// response, terms of the quadratic with one coefficient each, finite numbers, a scaling
    /// that divides by something. (A hand-edited or truncated file indexed out of bounds.)
    pub fn check(&self) -> Result<(), String> {
        let finite = |what: &str, values: &[f64]| match values.iter().find(|v| !v.is_finite()) {
            Some(v) => Err(format!("{what}: {v} is not a finite number")),
            None => Ok(()),
        };
        finite("leg_centre_mm", &self.leg_centre_mm)?;
        finite("leg_half_range_mm", &self.leg_half_range_mm)?;
        if let Some(h) = self.leg_half_range_mm.iter().find(|h| **h <= 0.0) {
            return Err(format!("leg_half_range_mm: {h} is not positive"));
        }
        if self.surfaces.len() != RESPONSES.len() {
            return Err(format!(
                "{} surfaces; a calibration has {} ({})",
                self.surfaces.len(),
                RESPONSES.len(),
                RESPONSES.join(", ")
            ));
        }
        for (s, name) in self.surfaces.iter().zip(RESPONSES) {
            if let Some(k) = s.terms.iter().find(|&&k| k >= TERMS) {
                return Err(format!(
                    "surface {name}: term {k}; the quadratic has terms 0 to {}",
                    TERMS - 1
                ));
            }
            if s.coefficients.len() != s.terms.len() {
                return Err(format!(
                    "surface {name}: {} coefficients for {} terms",
                    s.coefficients.len(),
                    s.terms.len()
                ));
            }
            finite(&format!("surface {name} coefficients"), &s.coefficients)?;
            finite(&format!("surface {name} sigma"), &[s.sigma])?;
        }
        if let Some(limit) = &self.leverage {
            if limit.moment_inverse.len() != TERMS * TERMS {
                return Err(format!(
                    "leverage: moment_inverse has {} entries, not {}",
                    limit.moment_inverse.len(),
                    TERMS * TERMS
                ));
            }
            finite("leverage moment_inverse", &limit.moment_inverse)?;
        }
        Ok(())
    }
}

/// How far from its data the full quadratic may be asked.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct LeverageLimit {
    /// (XᵀX)⁻¹ of the full quadratic over the measured legs (scaled), row-major.
    pub moment_inverse: Vec<f64>,
    /// The largest leverage of a measurement.
    pub max_measured: f64,
    /// How well an answer must be predicted to be given: the tool tip (mm) and the tilt
    /// (deg), as the standard error of a prediction, σ·√(1 + h).
    pub tolerance_mm: f64,
    pub tolerance_deg: f64,
}

/// The default tolerances: the seed's response surface reached 0.0205 mm and 0.0045° at its
/// example pose.
pub const DEFAULT_TOLERANCE_MM: f64 = 0.02;
pub const DEFAULT_TOLERANCE_DEG: f64 = 0.005;

impl LeverageLimit {
    fn of(xs: &[Vector3<f64>]) -> Option<LeverageLimit> {
        let x = DMatrix::from_fn(xs.len(), TERMS, |i, j| terms(&xs[i])[j]);
        let inverse = (x.transpose() * &x).try_inverse()?;
        let mut limit = LeverageLimit {
            moment_inverse: inverse.transpose().iter().copied().collect(),
            max_measured: 0.0,
            tolerance_mm: DEFAULT_TOLERANCE_MM,
            tolerance_deg: DEFAULT_TOLERANCE_DEG,
        };
        limit.max_measured = xs.iter().map(|x| limit.at(x)).fold(0.0, f64::max);
        Some(limit)
    }

    /// The leverage of scaled legs `x`.
    pub fn at(&self, x: &Vector3<f64>) -> f64 {
        let t = terms(x);
        let mut h = 0.0;
        for (i, ti) in t.iter().enumerate() {
            for (j, tj) in t.iter().enumerate() {
                h += ti * self.moment_inverse[i * TERMS + j] * tj;
            }
        }
        h
    }
}

/// (θ1, θ2) in degrees with θ2 ≥ 0 and θ1 unwrapped to within 180° of `reference_deg`: the
/// seed's variables, kept continuous over a region that does not contain θ2 = 0 (where θ1 is
/// undefined and the seed's normalisation θ1 ∈ (0°, 180°] would flip signs inside a fit).
fn tilt_deg(axis: &Vector3<f64>, reference_deg: f64) -> (f64, f64) {
    let w = Tilt::from_normal(axis);
    let t2 = w.angle_rad().to_degrees();
    let mut t1 = w.wy_rad.atan2(w.wx_rad).to_degrees();
    t1 += 360.0 * ((reference_deg - t1) / 360.0).round();
    (t1, t2)
}

/// The circular mean of the measured tilt directions, deg.
fn mean_direction_deg(data: &[Measurement]) -> f64 {
    let (mut x, mut y) = (0.0, 0.0);
    for m in data {
        let w = Tilt::from_normal(&m.axis);
        x += w.wx_rad;
        y += w.wy_rad;
    }
    y.atan2(x).to_degrees()
}

/// Fit the five response surfaces to measurements (α = `significance` for the t-tests).
pub fn fit_surfaces(
    data: &[Measurement],
    significance: f64,
) -> Result<ResponseSurfaces, CalibError> {
    if data.len() < TERMS + 1 {
        return Err(CalibError::TooFewMeasurements {
            have: data.len(),
            need: TERMS + 1,
        });
    }
    let mut lo = [f64::INFINITY; 3];
    let mut hi = [f64::NEG_INFINITY; 3];
    for m in data {
        for k in 0..3 {
            lo[k] = lo[k].min(m.legs_mm[k]);
            hi[k] = hi[k].max(m.legs_mm[k]);
        }
    }
    let centre = std::array::from_fn(|k| 0.5 * (lo[k] + hi[k]));
    let half: [f64; 3] = std::array::from_fn(|k| (0.5 * (hi[k] - lo[k])).max(1e-9));
    let xs: Vec<Vector3<f64>> = data
        .iter()
        .map(|m| Vector3::from_fn(|k, _| (m.legs_mm[k] - centre[k]) / half[k]))
        .collect();
    let reference = mean_direction_deg(data);
    let mut region = Region {
        tip_z_mm: [f64::INFINITY, f64::NEG_INFINITY],
        theta1_deg: [f64::INFINITY, f64::NEG_INFINITY],
        theta2_deg: [f64::INFINITY, f64::NEG_INFINITY],
    };
    let responses: Vec<DVector<f64>> = (0..5)
        .map(|r| {
            DVector::from_iterator(
                data.len(),
                data.iter().map(|m| {
                    let w = Tilt::from_normal(&m.axis);
                    [
                        m.tip_mm.x,
                        m.tip_mm.y,
                        m.tip_mm.z,
                        w.wx_rad.to_degrees(),
                        w.wy_rad.to_degrees(),
                    ][r]
                }),
            )
        })
        .collect();
    for m in data {
        let (t1, t2) = tilt_deg(&m.axis, reference);
        for (range, v) in [
            (&mut region.tip_z_mm, m.tip_mm.z),
            (&mut region.theta1_deg, t1),
            (&mut region.theta2_deg, t2),
        ] {
            range[0] = range[0].min(v);
            range[1] = range[1].max(v);
        }
    }
    let mut surfaces = Vec::with_capacity(5);
    for (r, y) in responses.iter().enumerate() {
        let all: Vec<usize> = (0..TERMS).collect();
        let full = fit(&xs, y, &all)?;
        let dof = (data.len() - TERMS) as f64;
        let t_crit = StudentsT::new(0.0, 1.0, dof)
            .map_err(|e| CalibError::Rsm(format!("t distribution: {e}")))?
            .inverse_cdf(1.0 - significance / 2.0);
        let kept: Vec<usize> = all
            .iter()
            .copied()
            .filter(|&k| k == 0 || full.t_values[k].abs() >= t_crit)
            .collect();
        let reduced = if kept.len() < TERMS {
            Some(fit(&xs, y, &kept)?)
        } else {
            None
        };
        let surface = match reduced {
            Some(red) if red.loo_mean_error < full.loo_mean_error => Surface {
                response: RESPONSES[r].into(),
                terms: kept,
                coefficients: red.coefficients,
                r2: red.r2,
                adjusted_r2: red.adjusted_r2,
                mean_error: red.loo_mean_error,
                sigma: red.sigma,
                other_mean_error: full.loo_mean_error,
                reduced: true,
            },
            other => Surface {
                response: RESPONSES[r].into(),
                terms: all,
                coefficients: full.coefficients,
                r2: full.r2,
                adjusted_r2: full.adjusted_r2,
                mean_error: full.loo_mean_error,
                sigma: full.sigma,
                other_mean_error: other.map_or(full.loo_mean_error, |f| f.loo_mean_error),
                reduced: false,
            },
        };
        surfaces.push(surface);
    }
    Ok(ResponseSurfaces {
        leg_centre_mm: centre,
        leg_half_range_mm: half,
        surfaces,
        region,
        significance,
        theta1_reference_deg: reference,
        leverage: LeverageLimit::of(&xs),
    })
}

impl ResponseSurfaces {
    fn legs(&self, x: &Vector3<f64>) -> [f64; 3] {
        std::array::from_fn(|k| self.leg_centre_mm[k] + x[k] * self.leg_half_range_mm[k])
    }

    /// Predicted tip and tilt vector (w_x, w_y) in degrees for commanded legs.
    pub fn predict(&self, legs_mm: [f64; 3]) -> ([f64; 3], [f64; 2]) {
        let x = Vector3::from_fn(|k, _| {
            (legs_mm[k] - self.leg_centre_mm[k]) / self.leg_half_range_mm[k]
        });
        let v: Vec<f64> = self.surfaces.iter().map(|s| s.value(&x)).collect();
        ([v[0], v[1], v[2]], [v[3], v[4]])
    }

    /// Legs (and table) that the surfaces say reach `target`; refused outside the region.
    pub fn solve(
        &self,
        geom: &Geometry,
        target: &ToolTarget,
    ) -> Result<CorrectedCommand, CalibError> {
        self.solve_with(geom, target, true)
    }

    /// Like [`ResponseSurfaces::solve`] but extrapolating outside the region (for studies of
    /// how badly a response surface extrapolates).
    pub fn solve_unchecked(
        &self,
        geom: &Geometry,
        target: &ToolTarget,
    ) -> Result<CorrectedCommand, CalibError> {
        self.solve_with(geom, target, false)
    }

    fn solve_with(
        &self,
        geom: &Geometry,
        target: &ToolTarget,
        checked: bool,
    ) -> Result<CorrectedCommand, CalibError> {
        let (t1, t2) = tilt_deg(&target.axis, self.theta1_reference_deg);
        let checks = [
            ("tool-tip Z (mm)", target.tip_mm.z, self.region.tip_z_mm),
            ("θ1 (deg)", t1, self.region.theta1_deg),
            ("θ2 (deg)", t2, self.region.theta2_deg),
        ];
        // With the data's leverage known, distance from the data decides (below); a file
        // without it keeps the box of the measured poses.
        let box_check = checked && self.leverage.is_none();
        for (what, value, range) in checks {
            if box_check && (value < range[0] - 1e-9 || value > range[1] + 1e-9) {
                return Err(CalibError::OutsideRegion {
                    what: what.into(),
                    value,
                    lo: range[0],
                    hi: range[1],
                });
            }
        }
        let nominal = geom.inverse_tool(&ToolTarget {
            tip_mm: Vector3::new(0.0, 0.0, target.tip_mm.z),
            axis: target.axis,
        })?;
        let mut x = Vector3::from_fn(|k, _| {
            (nominal.ik.legs_mm[k] - self.leg_centre_mm[k]) / self.leg_half_range_mm[k]
        });
        let w = Tilt::from_normal(&target.axis);
        let goal = Vector3::new(
            target.tip_mm.z,
            w.wx_rad.to_degrees(),
            w.wy_rad.to_degrees(),
        );
        for _ in 0..50 {
            let f = Vector3::new(
                self.surfaces[2].value(&x),
                self.surfaces[3].value(&x),
                self.surfaces[4].value(&x),
            ) - goal;
            if f.amax() < 1e-12 {
                break;
            }
            let j = Matrix3::from_rows(&[
                self.surfaces[2].gradient(&x).transpose(),
                self.surfaces[3].gradient(&x).transpose(),
                self.surfaces[4].gradient(&x).transpose(),
            ]);
            let step = j.lu().solve(&f).ok_or(CalibError::Rsm(
                "the response surfaces are singular at this target".into(),
            ))?;
            x -= step;
        }
        // Without the leverage, the legs must stay in the box of the measured legs (5 %
        // slack for the Newton answer).
        for k in 0..3 {
            if box_check && x[k].abs() > 1.05 {
                return Err(CalibError::OutsideRegion {
                    what: format!("leg L{} (scaled)", k + 1),
                    value: x[k],
                    lo: -1.0,
                    hi: 1.0,
                });
            }
        }
        let legs_mm = self.legs(&x);
        if let (true, Some(limit)) = (checked, &self.leverage) {
            let leverage = limit.at(&x);
            // (Written so that a diverged Newton answer, NaN, is refused too.)
            if leverage.is_nan() || leverage > limit.max_measured * (1.0 + 1e-9) {
                return Err(CalibError::Extrapolating {
                    legs_mm,
                    leverage,
                    max_measured: limit.max_measured,
                });
            }
            // The standard error of the answer: what the surfaces miss at their data,
            // grown by the distance from it.
            let spread = |rs: std::ops::Range<usize>| {
                self.surfaces[rs]
                    .iter()
                    .map(|s| s.sigma * s.sigma)
                    .sum::<f64>()
                    .sqrt()
                    * (1.0 + leverage).sqrt()
            };
            let (tip_mm, tilt_deg) = (spread(0..3), spread(3..5));
            if tip_mm.is_nan()
                || tilt_deg.is_nan()
                || tip_mm > limit.tolerance_mm
                || tilt_deg > limit.tolerance_deg
            {
                return Err(CalibError::Imprecise {
                    tip_mm,
                    tilt_deg,
                    tolerance_mm: limit.tolerance_mm,
                    tolerance_deg: limit.tolerance_deg,
                    leverage,
                });
            }
        }
        let (tip, _) = self.predict(legs_mm);
        Ok(CorrectedCommand {
            legs_mm,
            table_mm: [tip[0] - target.tip_mm.x, tip[1] - target.tip_mm.y],
        })
    }
}

/// A D-optimal design of `n` poses in `region` for the quadratic in the legs: a 6×6×6 grid of
/// candidates, improved by point exchange (Fedorov) until no swap raises det(XᵀX). Returns
/// the commanded legs and the D-efficiency |XᵀX|^(1/p)/n.
pub fn d_optimal_design(
    geom: &Geometry,
    region: &Region,
    n: usize,
) -> Result<(Vec<[f64; 3]>, f64), CalibError> {
    if n < TERMS {
        return Err(CalibError::TooFewMeasurements {
            have: n,
            need: TERMS,
        });
    }
    let grid = |r: [f64; 2], i: usize| r[0] + (r[1] - r[0]) * i as f64 / 5.0;
    let mut legs = Vec::new();
    for a in 0..6 {
        for b in 0..6 {
            for c in 0..6 {
                let axis = Tilt::from_theta(
                    grid(region.theta1_deg, b).to_radians(),
                    grid(region.theta2_deg, c).to_radians(),
                )
                .normal();
                let target = ToolTarget {
                    tip_mm: Vector3::new(0.0, 0.0, grid(region.tip_z_mm, a)),
                    axis,
                };
                legs.push(geom.inverse_tool(&target)?.ik.legs_mm);
            }
        }
    }
    let mut lo = [f64::INFINITY; 3];
    let mut hi = [f64::NEG_INFINITY; 3];
    for l in &legs {
        for k in 0..3 {
            lo[k] = lo[k].min(l[k]);
            hi[k] = hi[k].max(l[k]);
        }
    }
    let rows: Vec<[f64; TERMS]> = legs
        .iter()
        .map(|l| {
            terms(&Vector3::from_fn(|k, _| {
                (2.0 * l[k] - lo[k] - hi[k]) / (hi[k] - lo[k]).max(1e-9)
            }))
        })
        .collect();
    let det = |chosen: &[usize]| -> f64 {
        let m = DMatrix::from_fn(chosen.len(), TERMS, |i, j| rows[chosen[i]][j]);
        (m.transpose() * m).determinant()
    };
    // Start spread over the candidates, then exchange.
    let mut chosen: Vec<usize> = (0..n).map(|i| i * rows.len() / n).collect();
    let best = super::exchange(&mut chosen, rows.len(), true, usize::MAX, det, |d, best| {
        d > best * (1.0 + 1e-9)
    });
    let d_eff = best.max(0.0).powf(1.0 / TERMS as f64) / n as f64;
    Ok((chosen.iter().map(|&c| legs[c]).collect(), d_eff))
}
