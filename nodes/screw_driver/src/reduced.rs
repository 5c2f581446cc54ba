//! Reduced models of the outlet flow's response: first order plus dead time, or second order
//! plus dead time, fitted by least squares (Nelder–Mead from `argmin`) to a simulated or
//! measured step response. The screw driver's compensation uses the first-order form.

use argmin::core::{CostFunction, Error as ArgminError, Executor};
use argmin::solver::neldermead::NelderMead;

/// A unit-gain step response shape.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Reduced {
    /// `1 − exp(−(t − L)/τ)` after the dead time L.
    FirstOrder { tau_s: f64, dead_time_s: f64 },
    /// Two real poles τ1 ≥ τ2 after the dead time L.
    SecondOrder {
        tau1_s: f64,
        tau2_s: f64,
        dead_time_s: f64,
    },
}

impl Reduced {
    /// Fraction of a unit step reached `t` after the step.
    pub fn step(&self, t: f64) -> f64 {
        match *self {
            Reduced::FirstOrder { tau_s, dead_time_s } => {
                let s = t - dead_time_s;
                if s <= 0.0 {
                    0.0
                } else {
                    1.0 - (-s / tau_s).exp()
                }
            }
            Reduced::SecondOrder {
                tau1_s,
                tau2_s,
                dead_time_s,
            } => {
                let s = t - dead_time_s;
                if s <= 0.0 {
                    return 0.0;
                }
                if (tau1_s - tau2_s).abs() <= 1e-9 * tau1_s {
                    // Critically damped limit.
                    return 1.0 - (1.0 + s / tau1_s) * (-s / tau1_s).exp();
                }
                1.0 - (tau1_s * (-s / tau1_s).exp() - tau2_s * (-s / tau2_s).exp())
                    / (tau1_s - tau2_s)
            }
        }
    }

    /// The first-order form used for compensation: itself, or the second-order model's
    /// dominant pole with the faster one added to the dead time (Skogestad's half rule
    /// simplified to the whole).
    pub fn first_order(&self) -> (f64, f64) {
        match *self {
            Reduced::FirstOrder { tau_s, dead_time_s } => (tau_s, dead_time_s),
            Reduced::SecondOrder {
                tau1_s,
                tau2_s,
                dead_time_s,
            } => (tau1_s + 0.5 * tau2_s, dead_time_s + 0.5 * tau2_s),
        }
    }
}

/// A fit and its quality.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Fit {
    pub model: Reduced,
    /// RMS of (normalised response − model) over the samples.
    pub rms: f64,
}

/// Both fits of a step response and the one chosen.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Fits {
    pub first_order: Fit,
    pub second_order: Fit,
    /// Second order only where it halves the first order's RMS: a pole the data cannot
    /// resolve is not worth the parameter.
    pub chosen: Fit,
}

struct Cost<'a> {
    samples: &'a [(f64, f64)],
    second: bool,
}

fn model_of(p: &[f64], second: bool) -> Reduced {
    // Logs keep time constants positive; the dead time is squared to keep it ≥ 0.
    if second {
        let (a, b) = (p[0].exp(), p[1].exp());
        Reduced::SecondOrder {
            tau1_s: a.max(b),
            tau2_s: a.min(b),
            dead_time_s: p[2] * p[2],
        }
    } else {
        Reduced::FirstOrder {
            tau_s: p[0].exp(),
            dead_time_s: p[1] * p[1],
        }
    }
}

impl CostFunction for Cost<'_> {
    type Param = Vec<f64>;
    type Output = f64;
    fn cost(&self, p: &Vec<f64>) -> Result<f64, ArgminError> {
        let model = model_of(p, self.second);
        Ok(self
            .samples
            .iter()
            .map(|&(t, s)| (model.step(t) - s).powi(2))
            .sum())
    }
}

/// Normalise a step response `(t, y)` (t = 0 at the step) to the fraction of its change.
pub fn normalise(
    samples: &[(f64, f64)],
) -> Result<Vec<(f64, f64)>, crate::extruder::ExtruderError> {
    let (Some(first), Some(last)) = (samples.first(), samples.last()) else {
        return Err(crate::extruder::ExtruderError::NothingToFit {
            samples: 0,
            change: 0.0,
        });
    };
    let change = last.1 - first.1;
    if samples.len() < 8 || change.is_nan() || change == 0.0 {
        return Err(crate::extruder::ExtruderError::NothingToFit {
            samples: samples.len(),
            change,
        });
    }
    Ok(samples
        .iter()
        .map(|&(t, y)| (t, (y - first.1) / change))
        .collect())
}

/// Fit both models to a normalised step response (fractions from 0 to 1).
pub fn fit(normalised: &[(f64, f64)]) -> Fits {
    // Start from the 63 % time.
    let t63 = normalised
        .iter()
        .find(|&&(_, s)| s >= 1.0 - (-1.0f64).exp())
        .map_or(1.0, |&(t, _)| t.max(1e-9));
    let run = |second: bool| -> Fit {
        let start: Vec<f64> = if second {
            vec![(0.8 * t63).ln(), (0.2 * t63).ln(), 0.0]
        } else {
            vec![t63.ln(), 0.0]
        };
        let mut simplex = vec![start.clone()];
        for i in 0..start.len() {
            let mut v = start.clone();
            // The last parameter is √(dead time); the others are log time constants.
            v[i] += if i + 1 < start.len() {
                0.3
            } else {
                0.1 * t63.sqrt()
            };
            simplex.push(v);
        }
        let cost = Cost {
            samples: normalised,
            second,
        };
        let best = NelderMead::new(simplex)
            .with_sd_tolerance(1e-14)
            .ok()
            .and_then(|solver| {
                Executor::new(cost, solver)
                    .configure(|state| state.max_iters(4000))
                    .run()
                    .ok()
            })
            .and_then(|result| result.state.best_param.clone())
            .unwrap_or(start);
        let model = model_of(&best, second);
        let sse: f64 = normalised
            .iter()
            .map(|&(t, s)| (model.step(t) - s).powi(2))
            .sum();
        Fit {
            model,
            rms: (sse / normalised.len() as f64).sqrt(),
        }
    };
    let first_order = run(false);
    let second_order = run(true);
    let chosen = if second_order.rms < 0.5 * first_order.rms {
        second_order
    } else {
        first_order
    };
    Fits {
        first_order,
        second_order,
        chosen,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sampled(model: Reduced, dt: f64, n: usize) -> Vec<(f64, f64)> {
        (0..n)
            .map(|k| (k as f64 * dt, model.step(k as f64 * dt)))
            .collect()
    }

    #[test]
    fn recovers_a_first_order_model() {
        let truth = Reduced::FirstOrder {
            tau_s: 0.02,
            dead_time_s: 0.005,
        };
        let fits = fit(&sampled(truth, 0.0005, 300));
        let Reduced::FirstOrder { tau_s, dead_time_s } = fits.chosen.model else {
            panic!("{fits:?}")
        };
        assert!((tau_s - 0.02).abs() < 1e-5, "{fits:?}");
        assert!((dead_time_s - 0.005).abs() < 1e-5, "{fits:?}");
    }

    #[test]
    fn recovers_a_second_order_model_and_prefers_it() {
        let truth = Reduced::SecondOrder {
            tau1_s: 0.03,
            tau2_s: 0.012,
            dead_time_s: 0.0,
        };
        let fits = fit(&sampled(truth, 0.0005, 400));
        let Reduced::SecondOrder { tau1_s, tau2_s, .. } = fits.chosen.model else {
            panic!("{fits:?}")
        };
        assert!((tau1_s - 0.03).abs() < 3e-4, "{fits:?}");
        assert!((tau2_s - 0.012).abs() < 3e-4, "{fits:?}");
        assert!(fits.first_order.rms > 2.0 * fits.second_order.rms);
    }

    #[test]
    fn second_order_step_matches_its_closed_form_limits() {
        let m = Reduced::SecondOrder {
            tau1_s: 1.0,
            tau2_s: 1.0,
            dead_time_s: 0.0,
        };
        assert!((m.step(1.0) - (1.0 - 2.0 * (-1.0f64).exp())).abs() < 1e-12);
        let nearly = Reduced::SecondOrder {
            tau1_s: 1.0,
            tau2_s: 0.999_999,
            dead_time_s: 0.0,
        };
        assert!((nearly.step(1.0) - m.step(1.0)).abs() < 1e-6);
    }
}
