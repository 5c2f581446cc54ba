//! 2-D incompressible Navier–Stokes by the fractional-step method on a staggered (MAC) grid,
//! as seed 000 sets it up (eqs. 18–25) to study the screw's output delay.
//!
//! * Grid: `u` on the vertical cell faces, `v` on the horizontal ones, `p` at the centres
//!   (the seed's staggered grid); walls lie on cell faces, tangential wall speeds enter through
//!   ghost values (`u_ghost = 2·U_wall − u_inside`), which keeps the scheme second order.
//! * Step: the seed's predictor (eq. 21) with central differences for advection and diffusion,
//!   advanced by second-order Adams–Bashforth instead of the seed's forward Euler (forward
//!   Euler with central advection is unstable without enough viscosity); then the pressure
//!   Poisson equation (eq. 25) `∇²p = ∇·v*/Δt` and the correction `v = v* − Δt ∇p` (eq. 24).
//! * Pressure: the 5-point Laplacian with the MAC grid's Neumann walls is diagonalised exactly
//!   by cosine transforms (and by the Fourier transform along a periodic direction), so the
//!   Poisson equation is solved directly, to rounding, in O(N log N) — faster than conjugate
//!   gradients, which would need hundreds of iterations a step on the 129×129 cavity, and
//!   without a tolerance to tune. [`PoissonSolver`] is tested for its residual.
//!
//! Non-dimensional or SI: the solver sees a kinematic viscosity ν and lengths; `ν = 1/Re` with
//! unit lengths and wall speed is the seed's non-dimensional form.

pub mod ghia;

use std::sync::Arc;

use rustdct::rustfft::{num_complex::Complex, Fft, FftPlanner};
use rustdct::{DctPlanner, TransformType2And3};

/// What bounds the domain left and right.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SidesX {
    /// No-slip, impermeable walls at x = 0 and x = length_x (a cavity, a screw flight).
    Walls,
    /// The flow repeats with period length_x (a fully developed channel).
    Periodic,
}

/// A flow problem: domain, fluid, boundaries, forcing.
#[derive(Clone, Debug, PartialEq)]
pub struct FlowOptions {
    pub cells_x: usize,
    pub cells_y: usize,
    pub length_x: f64,
    pub length_y: f64,
    /// ν = μ/ρ (1/Re in the non-dimensional form).
    pub kinematic_viscosity: f64,
    pub sides_x: SidesX,
    /// Tangential (x) speed of the wall at y = 0 and of the wall at y = length_y.
    pub wall_speed_bottom: f64,
    pub wall_speed_top: f64,
    /// Uniform body force along x per unit mass (a driving pressure gradient −(1/ρ)∂p/∂x).
    pub body_force_x: f64,
    /// Courant number bound of the adaptive time step.
    pub courant: f64,
    /// Diffusion number bound `ν Δt (1/Δx² + 1/Δy²)` of the adaptive time step.
    pub diffusion_number: f64,
}

impl Default for FlowOptions {
    /// The lid-driven unit cavity at Re = 100 on 64×64 cells.
    fn default() -> Self {
        FlowOptions {
            cells_x: 64,
            cells_y: 64,
            length_x: 1.0,
            length_y: 1.0,
            kinematic_viscosity: 0.01,
            sides_x: SidesX::Walls,
            wall_speed_bottom: 0.0,
            wall_speed_top: 1.0,
            body_force_x: 0.0,
            courant: 0.4,
            diffusion_number: 0.2,
        }
    }
}

/// Why a flow cannot be set up.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum FlowError {
    #[error("flow option {name} is {value}: {why}")]
    Option {
        name: &'static str,
        value: f64,
        why: &'static str,
    },
    #[error("the flow diverged at t = {t} (step {step}): max speed {speed}")]
    Diverged { t: f64, step: u64, speed: f64 },
}

type FftPair = (Arc<dyn Fft<f64>>, Arc<dyn Fft<f64>>);

/// Solves `∇²φ = f` on the cell centres with zero normal gradient on walls (and periodicity
/// along x where chosen), the discrete 5-point Laplacian exactly. The solution has zero mean.
pub struct PoissonSolver {
    nx: usize,
    ny: usize,
    dct_x: Arc<dyn TransformType2And3<f64>>,
    dct_y: Arc<dyn TransformType2And3<f64>>,
    /// Forward and inverse transforms along a periodic x.
    fft_x: Option<FftPair>,
    eigen_x: Vec<f64>,
    eigen_y: Vec<f64>,
    column: Vec<f64>,
    complex: Vec<Complex<f64>>,
}

impl PoissonSolver {
    pub fn new(nx: usize, ny: usize, dx: f64, dy: f64, sides_x: SidesX) -> Self {
        let mut planner = DctPlanner::new();
        let (eigen_x, fft_x) = match sides_x {
            SidesX::Walls => (
                (0..nx)
                    .map(|k| {
                        (2.0 * (std::f64::consts::PI * k as f64 / nx as f64).cos() - 2.0)
                            / (dx * dx)
                    })
                    .collect(),
                None,
            ),
            SidesX::Periodic => {
                let mut fft = FftPlanner::new();
                (
                    (0..nx)
                        .map(|k| {
                            (2.0 * (2.0 * std::f64::consts::PI * k as f64 / nx as f64).cos() - 2.0)
                                / (dx * dx)
                        })
                        .collect(),
                    Some((fft.plan_fft_forward(nx), fft.plan_fft_inverse(nx))),
                )
            }
        };
        let eigen_y = (0..ny)
            .map(|k| (2.0 * (std::f64::consts::PI * k as f64 / ny as f64).cos() - 2.0) / (dy * dy))
            .collect();
        PoissonSolver {
            nx,
            ny,
            dct_x: planner.plan_dct2(nx),
            dct_y: planner.plan_dct2(ny),
            fft_x,
            eigen_x,
            eigen_y,
            column: vec![0.0; ny],
            complex: vec![Complex::default(); nx * ny],
        }
    }

    /// Overwrites `f` (row-major, x fastest) with φ.
    pub fn solve(&mut self, f: &mut [f64]) {
        let (nx, ny) = (self.nx, self.ny);
        assert_eq!(f.len(), nx * ny, "Poisson right-hand side size");
        match &self.fft_x {
            None => {
                for row in f.chunks_exact_mut(nx) {
                    self.dct_x.process_dct2(row);
                }
                for_each_column(f, nx, ny, &mut self.column, |c| self.dct_y.process_dct2(c));
                for j in 0..ny {
                    for i in 0..nx {
                        let lambda = self.eigen_x[i] + self.eigen_y[j];
                        f[j * nx + i] = if i == 0 && j == 0 {
                            0.0
                        } else {
                            f[j * nx + i] / lambda
                        };
                    }
                }
                for_each_column(f, nx, ny, &mut self.column, |c| self.dct_y.process_dct3(c));
                for row in f.chunks_exact_mut(nx) {
                    self.dct_x.process_dct3(row);
                }
                // DCT-III ∘ DCT-II = n/2 along each direction.
                let scale = 4.0 / (nx * ny) as f64;
                f.iter_mut().for_each(|x| *x *= scale);
            }
            Some((forward, inverse)) => {
                let z = &mut self.complex;
                for (zi, fi) in z.iter_mut().zip(f.iter()) {
                    *zi = Complex::new(*fi, 0.0);
                }
                for row in z.chunks_exact_mut(nx) {
                    forward.process(row);
                }
                // Cosine transform along y of the real and imaginary parts.
                for part in 0..2 {
                    for i in 0..nx {
                        for j in 0..ny {
                            let c = z[j * nx + i];
                            self.column[j] = if part == 0 { c.re } else { c.im };
                        }
                        self.dct_y.process_dct2(&mut self.column);
                        for j in 0..ny {
                            let lambda = self.eigen_x[i] + self.eigen_y[j];
                            let value = if i == 0 && j == 0 {
                                0.0
                            } else {
                                self.column[j] / lambda
                            };
                            self.column[j] = value;
                        }
                        self.dct_y.process_dct3(&mut self.column);
                        for j in 0..ny {
                            let c = &mut z[j * nx + i];
                            if part == 0 {
                                c.re = self.column[j];
                            } else {
                                c.im = self.column[j];
                            }
                        }
                    }
                }
                for row in z.chunks_exact_mut(nx) {
                    inverse.process(row);
                }
                let scale = 2.0 / (nx * ny) as f64;
                for (fi, zi) in f.iter_mut().zip(z.iter()) {
                    *fi = zi.re * scale;
                }
            }
        }
    }
}

fn for_each_column(
    f: &mut [f64],
    nx: usize,
    ny: usize,
    column: &mut [f64],
    mut transform: impl FnMut(&mut [f64]),
) {
    for i in 0..nx {
        for j in 0..ny {
            column[j] = f[j * nx + i];
        }
        transform(column);
        for j in 0..ny {
            f[j * nx + i] = column[j];
        }
    }
}

/// The flow state and its stepper.
pub struct Flow {
    options: FlowOptions,
    dx: f64,
    dy: f64,
    /// x faces: `nux = nx + 1` with walls (both wall faces stored, always 0), `nx` periodic.
    nux: usize,
    u: Vec<f64>,
    v: Vec<f64>,
    p: Vec<f64>,
    rhs_u_prev: Vec<f64>,
    rhs_v_prev: Vec<f64>,
    rhs_u: Vec<f64>,
    rhs_v: Vec<f64>,
    dt_prev: f64,
    poisson: PoissonSolver,
    divergence: Vec<f64>,
    time: f64,
    steps: u64,
    /// max |Δu|/Δt over the last step: 0 at a steady state.
    last_rate: f64,
}

impl Flow {
    /// A fluid at rest.
    pub fn new(options: FlowOptions) -> Result<Flow, FlowError> {
        let check = |name, value: f64, ok: bool, why| {
            if ok {
                Ok(())
            } else {
                Err(FlowError::Option { name, value, why })
            }
        };
        let o = &options;
        check(
            "cells_x",
            o.cells_x as f64,
            o.cells_x >= 2,
            "at least 2 cells",
        )?;
        check(
            "cells_y",
            o.cells_y as f64,
            o.cells_y >= 2,
            "at least 2 cells",
        )?;
        for (name, value) in [
            ("length_x", o.length_x),
            ("length_y", o.length_y),
            ("kinematic_viscosity", o.kinematic_viscosity),
            ("courant", o.courant),
            ("diffusion_number", o.diffusion_number),
        ] {
            check(
                name,
                value,
                value.is_finite() && value > 0.0,
                "must be finite and > 0",
            )?;
        }
        for (name, value) in [
            ("wall_speed_bottom", o.wall_speed_bottom),
            ("wall_speed_top", o.wall_speed_top),
            ("body_force_x", o.body_force_x),
        ] {
            check(name, value, value.is_finite(), "must be finite")?;
        }
        check(
            "diffusion_number",
            o.diffusion_number,
            o.diffusion_number <= 0.25,
            "Adams–Bashforth diffusion is stable up to 0.25",
        )?;
        let (nx, ny) = (o.cells_x, o.cells_y);
        let dx = o.length_x / nx as f64;
        let dy = o.length_y / ny as f64;
        let nux = match o.sides_x {
            SidesX::Walls => nx + 1,
            SidesX::Periodic => nx,
        };
        Ok(Flow {
            poisson: PoissonSolver::new(nx, ny, dx, dy, o.sides_x),
            dx,
            dy,
            nux,
            u: vec![0.0; nux * ny],
            v: vec![0.0; nx * (ny + 1)],
            p: vec![0.0; nx * ny],
            rhs_u_prev: vec![0.0; nux * ny],
            rhs_v_prev: vec![0.0; nx * (ny + 1)],
            rhs_u: vec![0.0; nux * ny],
            rhs_v: vec![0.0; nx * (ny + 1)],
            divergence: vec![0.0; nx * ny],
            dt_prev: 0.0,
            time: 0.0,
            steps: 0,
            last_rate: f64::INFINITY,
            options,
        })
    }

    pub fn options(&self) -> &FlowOptions {
        &self.options
    }
    pub fn time(&self) -> f64 {
        self.time
    }
    pub fn steps(&self) -> u64 {
        self.steps
    }
    /// max |∂u/∂t|, |∂v/∂t| over the last step.
    pub fn rate_of_change(&self) -> f64 {
        self.last_rate
    }

    /// Change the walls' speeds or the body force (a step input); the state is kept.
    pub fn set_forcing(&mut self, wall_speed_bottom: f64, wall_speed_top: f64, body_force_x: f64) {
        self.options.wall_speed_bottom = wall_speed_bottom;
        self.options.wall_speed_top = wall_speed_top;
        self.options.body_force_x = body_force_x;
    }

    #[inline]
    fn u_at(&self, i: isize, j: isize) -> f64 {
        let o = &self.options;
        let ny = o.cells_y as isize;
        if j < 0 {
            return 2.0 * o.wall_speed_bottom - self.u_at(i, 0);
        }
        if j >= ny {
            return 2.0 * o.wall_speed_top - self.u_at(i, ny - 1);
        }
        let i = match o.sides_x {
            SidesX::Periodic => i.rem_euclid(self.nux as isize),
            SidesX::Walls => i.clamp(0, self.nux as isize - 1),
        };
        self.u[j as usize * self.nux + i as usize]
    }

    #[inline]
    fn v_at(&self, i: isize, j: isize) -> f64 {
        let o = &self.options;
        let nx = o.cells_x as isize;
        let j = j.clamp(0, o.cells_y as isize);
        match o.sides_x {
            SidesX::Periodic => self.v[j as usize * o.cells_x + i.rem_euclid(nx) as usize],
            // Impermeable walls at rest: the tangential v is mirrored to 0 on the wall.
            SidesX::Walls if i < 0 => -self.v_at(0, j),
            SidesX::Walls if i >= nx => -self.v_at(nx - 1, j),
            SidesX::Walls => self.v[j as usize * o.cells_x + i as usize],
        }
    }

    /// The adaptive step: bounded by the Courant number on the current speeds (walls
    /// included) and by the diffusion number.
    pub fn stable_dt(&self) -> f64 {
        let o = &self.options;
        let speed = self.u.iter().chain(&self.v).fold(
            o.wall_speed_top.abs().max(o.wall_speed_bottom.abs()),
            |m, x| m.max(x.abs()),
        );
        let h = self.dx.min(self.dy);
        let diffusive = o.diffusion_number
            / (o.kinematic_viscosity * (1.0 / (self.dx * self.dx) + 1.0 / (self.dy * self.dy)));
        if speed > 0.0 {
            diffusive.min(o.courant * h / speed)
        } else {
            diffusive
        }
    }

    /// One fractional step of length `dt`.
    pub fn step(&mut self, dt: f64) -> Result<(), FlowError> {
        let o = self.options.clone();
        let (nx, ny) = (o.cells_x, o.cells_y);
        let (dx, dy) = (self.dx, self.dy);
        let nu = o.kinematic_viscosity;
        let (idx2, idy2) = (1.0 / (dx * dx), 1.0 / (dy * dy));
        // Predictor right-hand sides (seed eq. 21 / 26).
        let first_face = match o.sides_x {
            SidesX::Walls => 1,
            SidesX::Periodic => 0,
        };
        let last_face = nx;
        for j in 0..ny as isize {
            for i in first_face as isize..last_face as isize {
                let c = self.u_at(i, j);
                let (e, w, n, s) = (
                    self.u_at(i + 1, j),
                    self.u_at(i - 1, j),
                    self.u_at(i, j + 1),
                    self.u_at(i, j - 1),
                );
                let v_mean = 0.25
                    * (self.v_at(i - 1, j)
                        + self.v_at(i, j)
                        + self.v_at(i - 1, j + 1)
                        + self.v_at(i, j + 1));
                let advection = c * (e - w) / (2.0 * dx) + v_mean * (n - s) / (2.0 * dy);
                let laplacian = (e - 2.0 * c + w) * idx2 + (n - 2.0 * c + s) * idy2;
                self.rhs_u[j as usize * self.nux + i as usize] =
                    -advection + nu * laplacian + o.body_force_x;
            }
        }
        for j in 1..ny as isize {
            for i in 0..nx as isize {
                let c = self.v_at(i, j);
                let (e, w, n, s) = (
                    self.v_at(i + 1, j),
                    self.v_at(i - 1, j),
                    self.v_at(i, j + 1),
                    self.v_at(i, j - 1),
                );
                let u_mean = 0.25
                    * (self.u_at(i, j - 1)
                        + self.u_at(i + 1, j - 1)
                        + self.u_at(i, j)
                        + self.u_at(i + 1, j));
                let advection = u_mean * (e - w) / (2.0 * dx) + c * (n - s) / (2.0 * dy);
                let laplacian = (e - 2.0 * c + w) * idx2 + (n - 2.0 * c + s) * idy2;
                self.rhs_v[j as usize * nx + i as usize] = -advection + nu * laplacian;
            }
        }
        // Adams–Bashforth 2 with a variable step (forward Euler on the first).
        let (a, b) = if self.steps == 0 || self.dt_prev <= 0.0 {
            (1.0, 0.0)
        } else {
            let ratio = dt / self.dt_prev;
            (1.0 + 0.5 * ratio, -0.5 * ratio)
        };
        let mut rate: f64 = 0.0;
        let u_before = self.u.clone();
        let v_before = self.v.clone();
        for j in 0..ny {
            for i in first_face..last_face {
                let k = j * self.nux + i;
                self.u[k] += dt * (a * self.rhs_u[k] + b * self.rhs_u_prev[k]);
            }
        }
        for j in 1..ny {
            for i in 0..nx {
                let k = j * nx + i;
                self.v[k] += dt * (a * self.rhs_v[k] + b * self.rhs_v_prev[k]);
            }
        }
        std::mem::swap(&mut self.rhs_u, &mut self.rhs_u_prev);
        std::mem::swap(&mut self.rhs_v, &mut self.rhs_v_prev);
        // Pressure (eq. 25) and correction (eq. 24).
        for j in 0..ny {
            for i in 0..nx {
                let (ii, jj) = (i as isize, j as isize);
                let div = (self.u_at(ii + 1, jj) - self.u_at(ii, jj)) / dx
                    + (self.v_at(ii, jj + 1) - self.v_at(ii, jj)) / dy;
                self.divergence[j * nx + i] = div / dt;
            }
        }
        self.poisson.solve(&mut self.divergence);
        std::mem::swap(&mut self.p, &mut self.divergence);
        let p_at = |p: &[f64], i: isize, j: usize| p[j * nx + i.rem_euclid(nx as isize) as usize];
        for j in 0..ny {
            for i in first_face..last_face {
                let ii = i as isize;
                self.u[j * self.nux + i] -=
                    dt * (p_at(&self.p, ii, j) - p_at(&self.p, ii - 1, j)) / dx;
            }
        }
        for j in 1..ny {
            for i in 0..nx {
                self.v[j * nx + i] -= dt * (self.p[j * nx + i] - self.p[(j - 1) * nx + i]) / dy;
            }
        }
        for (now, before) in self
            .u
            .iter()
            .zip(&u_before)
            .chain(self.v.iter().zip(&v_before))
        {
            rate = rate.max((now - before).abs() / dt);
        }
        self.dt_prev = dt;
        self.time += dt;
        self.steps += 1;
        self.last_rate = rate;
        let speed = self
            .u
            .iter()
            .chain(&self.v)
            .fold(0.0f64, |m, x| m.max(x.abs()));
        if !speed.is_finite()
            || speed > 1e6 * (1.0 + o.wall_speed_top.abs() + o.wall_speed_bottom.abs())
        {
            return Err(FlowError::Diverged {
                t: self.time,
                step: self.steps,
                speed,
            });
        }
        Ok(())
    }

    /// Step with the adaptive step until `t_end`.
    pub fn advance_to(&mut self, t_end: f64) -> Result<(), FlowError> {
        while self.time < t_end {
            let dt = self.stable_dt().min(t_end - self.time);
            if dt <= 0.0 {
                break;
            }
            self.step(dt)?;
        }
        Ok(())
    }

    /// Step until max |∂v/∂t| < `tolerance` or the time reaches `t_max`; returns whether it
    /// became steady.
    pub fn run_to_steady(&mut self, tolerance: f64, t_max: f64) -> Result<bool, FlowError> {
        while self.time < t_max {
            let dt = self.stable_dt();
            self.step(dt)?;
            if self.last_rate < tolerance {
                return Ok(true);
            }
        }
        Ok(false)
    }

    /// u at a point (bilinear on the u grid; walls through their ghosts).
    pub fn u_velocity(&self, x: f64, y: f64) -> f64 {
        let fi = x / self.dx;
        let fj = y / self.dy - 0.5;
        self.bilinear(fi, fj, |i, j| self.u_at(i, j))
    }

    /// v at a point (bilinear on the v grid).
    pub fn v_velocity(&self, x: f64, y: f64) -> f64 {
        let fi = x / self.dx - 0.5;
        let fj = y / self.dy;
        self.bilinear(fi, fj, |i, j| self.v_at(i, j))
    }

    fn bilinear(&self, fi: f64, fj: f64, at: impl Fn(isize, isize) -> f64) -> f64 {
        let (i0, j0) = (fi.floor(), fj.floor());
        let (sx, sy) = (fi - i0, fj - j0);
        let (i0, j0) = (i0 as isize, j0 as isize);
        let a = at(i0, j0) * (1.0 - sx) + at(i0 + 1, j0) * sx;
        let b = at(i0, j0 + 1) * (1.0 - sx) + at(i0 + 1, j0 + 1) * sx;
        a * (1.0 - sy) + b * sy
    }

    /// u at the centre of cell row `j` on face column `i`.
    pub fn u_face(&self, i: usize, j: usize) -> f64 {
        self.u[j * self.nux + i]
    }

    /// Flow rate across the face column `i` per unit depth: Σ u Δy.
    pub fn flow_rate_x(&self, i: usize) -> f64 {
        (0..self.options.cells_y)
            .map(|j| self.u_face(i, j) * self.dy)
            .sum()
    }

    /// Largest |∇·v| over the cells (0 to rounding after each step).
    pub fn max_divergence(&self) -> f64 {
        let (nx, ny) = (self.options.cells_x, self.options.cells_y);
        let mut worst: f64 = 0.0;
        for j in 0..ny as isize {
            for i in 0..nx as isize {
                let div = (self.u_at(i + 1, j) - self.u_at(i, j)) / self.dx
                    + (self.v_at(i, j + 1) - self.v_at(i, j)) / self.dy;
                worst = worst.max(div.abs());
            }
        }
        worst
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The discrete Laplacian of the solver's answer gives back the right-hand side.
    fn residual(nx: usize, ny: usize, sides: SidesX) -> f64 {
        let (dx, dy) = (1.0 / nx as f64, 0.7 / ny as f64);
        let mut solver = PoissonSolver::new(nx, ny, dx, dy, sides);
        // A right-hand side with zero mean (the Neumann problem's compatibility).
        let mut f: Vec<f64> = (0..nx * ny)
            .map(|k| ((k * 7919) % 101) as f64 / 50.0 - 1.0)
            .collect();
        let mean = f.iter().sum::<f64>() / f.len() as f64;
        f.iter_mut().for_each(|x| *x -= mean);
        let rhs = f.clone();
        solver.solve(&mut f);
        let at = |i: isize, j: isize| {
            let j = j.clamp(0, ny as isize - 1) as usize;
            let i = match sides {
                SidesX::Walls => i.clamp(0, nx as isize - 1) as usize,
                SidesX::Periodic => i.rem_euclid(nx as isize) as usize,
            };
            f[j * nx + i]
        };
        let mut worst: f64 = 0.0;
        for j in 0..ny as isize {
            for i in 0..nx as isize {
                let lap = (at(i + 1, j) - 2.0 * at(i, j) + at(i - 1, j)) / (dx * dx)
                    + (at(i, j + 1) - 2.0 * at(i, j) + at(i, j - 1)) / (dy * dy);
                worst = worst.max((lap - rhs[j as usize * nx + i as usize]).abs());
            }
        }
        worst
    }

    #[test]
    fn poisson_solver_is_exact_to_rounding() {
        for (nx, ny) in [(8, 8), (16, 12), (33, 17)] {
            for sides in [SidesX::Walls, SidesX::Periodic] {
                let r = residual(nx, ny, sides);
                assert!(r < 1e-9, "{nx}×{ny} {sides:?}: residual {r}");
            }
        }
    }

    /// Plane Couette–Poiseuille flow between a wall at rest (y = 0) and one moving at U
    /// (y = H), driven also by a pressure gradient G = −(1/ρ)∂p/∂x: steady
    /// u(y) = U y/H + G/(2ν) · y (H − y). Returns the largest error at the cell centres and the
    /// flow rate error.
    fn couette_poiseuille_error(cells: usize) -> (f64, f64) {
        let (wall, force, nu, h) = (1.0, 6.0, 0.5, 1.0);
        let mut flow = Flow::new(FlowOptions {
            cells_x: 4,
            cells_y: cells,
            length_x: 1.0,
            length_y: h,
            kinematic_viscosity: nu,
            sides_x: SidesX::Periodic,
            wall_speed_bottom: 0.0,
            wall_speed_top: wall,
            body_force_x: force,
            ..FlowOptions::default()
        })
        .unwrap();
        let steady = flow.run_to_steady(1e-9, 50.0).unwrap();
        assert!(
            steady,
            "steady: rate {} at t {}",
            flow.rate_of_change(),
            flow.time()
        );
        let exact = |y: f64| wall * y / h + force / (2.0 * nu) * y * (h - y);
        let dy = h / cells as f64;
        let mut worst: f64 = 0.0;
        for j in 0..cells {
            let y = (j as f64 + 0.5) * dy;
            for i in 0..4 {
                worst = worst.max((flow.u_face(i, j) - exact(y)).abs());
            }
        }
        let q_exact = wall * h / 2.0 + force * h.powi(3) / (12.0 * nu);
        (worst, (flow.flow_rate_x(0) - q_exact).abs())
    }

    #[test]
    fn couette_poiseuille_converges_at_second_order() {
        let errors: Vec<(f64, f64)> = [8, 16, 32]
            .iter()
            .map(|&n| couette_poiseuille_error(n))
            .collect();
        for w in errors.windows(2) {
            let order = (w[0].0 / w[1].0).log2();
            let order_q = (w[0].1 / w[1].1).log2();
            assert!(
                (1.9..2.1).contains(&order),
                "velocity order {order}: {errors:?}"
            );
            assert!(
                (1.9..2.1).contains(&order_q),
                "flow-rate order {order_q}: {errors:?}"
            );
        }
        assert!(errors[2].0 < 2e-3, "{errors:?}");
    }

    #[test]
    fn a_cavity_stays_divergence_free() {
        let mut flow = Flow::new(FlowOptions {
            cells_x: 24,
            cells_y: 16,
            length_y: 0.7,
            ..FlowOptions::default()
        })
        .unwrap();
        flow.advance_to(0.5).unwrap();
        assert!(flow.max_divergence() < 1e-9, "{}", flow.max_divergence());
        // The lid drags the fluid along under it.
        assert!(flow.u_velocity(0.5, 0.68) > 0.3);
    }

    #[test]
    fn bad_options_are_refused_by_name() {
        let err = Flow::new(FlowOptions {
            kinematic_viscosity: f64::NAN,
            ..FlowOptions::default()
        })
        .err()
        .unwrap();
        assert!(err.to_string().contains("kinematic_viscosity"), "{err}");
        let err = Flow::new(FlowOptions {
            diffusion_number: 0.9,
            ..FlowOptions::default()
        })
        .err()
        .unwrap();
        assert!(err.to_string().contains("0.25"), "{err}");
    }
}
