//! Cartesian lines as joint-space paths of the polar machine (θ bed, r arm, z).
//!
//! A point is `(x, y, z) = (r cos θ, r sin θ, z)`. θ is continuous: it is never re-based, so it
//! can run any number of turns either way (the seam of seed 000 §5.2 cannot happen). `r` is
//! non-negative unless negative radii are allowed.
//!
//! Two kinds of line:
//! * **radial** — the line's support passes through the centre (or a z-only move): θ is
//!   constant and r, z are linear in the path length, so joint-space interpolation is exact;
//! * **general** — θ and r are smooth but curved functions of the path length; the line is
//!   split into pieces whose joint-space chords stay within the path tolerance.
//!
//! Derivatives with respect to the path length `s` (3-D arc length) are analytic:
//! with `p` the xy position, `u` the unit 3-D direction and `c = p × u_xy`,
//! `θ' = c/|p|²`, `θ'' = −2c(p·u)/|p|⁴`, `r' = σ(p·u)/|p|`, `r'' = σc²/|p|³`, `z' = u_z`.

/// Joint coordinates `[θ (rad), r (m), z (m)]`.
pub type Joints = [f64; 3];

/// A joint-space point of a line with its path derivatives.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PathNode {
    /// Path length from the start of the line (m).
    pub s: f64,
    pub q: Joints,
    /// dq/ds.
    pub dq: Joints,
    /// d²q/ds².
    pub ddq: Joints,
}

/// One straight Cartesian segment and its joint-space representation.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Line {
    /// Start and end, Cartesian (m).
    pub a: [f64; 3],
    pub b: [f64; 3],
    /// Joints at the start (θ chosen for continuity, r signed).
    pub q_a: Joints,
    /// +1 when r is non-negative along the line, −1 when negative (general lines only).
    pub sign: f64,
    /// True when θ is constant along the line.
    pub radial: bool,
}

impl Line {
    pub fn length(&self) -> f64 {
        dist3(self.a, self.b)
    }

    fn unit(&self) -> [f64; 3] {
        let l = self.length();
        if l == 0.0 {
            return [0.0; 3];
        }
        [
            (self.b[0] - self.a[0]) / l,
            (self.b[1] - self.a[1]) / l,
            (self.b[2] - self.a[2]) / l,
        ]
    }

    /// Cartesian point at path length `s`.
    pub fn point(&self, s: f64) -> [f64; 3] {
        let u = self.unit();
        [
            self.a[0] + u[0] * s,
            self.a[1] + u[1] * s,
            self.a[2] + u[2] * s,
        ]
    }

    /// Joints and derivatives at path length `s`.
    pub fn node(&self, s: f64) -> PathNode {
        let u = self.unit();
        let z = self.q_a[2] + u[2] * s;
        if self.radial {
            // r changes at the rate of the xy motion projected on the (fixed) θ direction.
            let (sin_t, cos_t) = self.q_a[0].sin_cos();
            let dr = u[0] * cos_t + u[1] * sin_t;
            return PathNode {
                s,
                q: [self.q_a[0], self.q_a[1] + dr * s, z],
                dq: [0.0, dr, u[2]],
                ddq: [0.0, 0.0, 0.0],
            };
        }
        let p = self.point(s);
        let (px, py) = (p[0], p[1]);
        let rr = px * px + py * py;
        let r = rr.sqrt();
        let c = px * u[1] - py * u[0];
        let pu = px * u[0] + py * u[1];
        let pa = [self.a[0], self.a[1]];
        // θ increment from the start: the angle swept by the xy position (< π on a line that
        // misses the centre), the same for either sign of r.
        let sweep = (pa[0] * py - pa[1] * px).atan2(pa[0] * px + pa[1] * py);
        PathNode {
            s,
            q: [self.q_a[0] + sweep, self.sign * r, z],
            dq: [c / rr, self.sign * pu / r, u[2]],
            ddq: [-2.0 * c * pu / (rr * rr), self.sign * c * c / (rr * r), 0.0],
        }
    }

    /// Joints at the end of the line.
    pub fn q_b(&self) -> Joints {
        self.node(self.length()).q
    }
}

pub fn dist3(a: [f64; 3], b: [f64; 3]) -> f64 {
    ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt()
}

/// Cartesian position of joints.
pub fn forward(q: Joints) -> [f64; 3] {
    let (s, c) = q[0].sin_cos();
    [q[1] * c, q[1] * s, q[2]]
}

/// The angle nearest to `reference` that points the arm at `(x, y)` with the given sign of r.
pub fn continuous_theta(x: f64, y: f64, reference: f64, sign: f64) -> f64 {
    let mut angle = y.atan2(x);
    if sign < 0.0 {
        angle += std::f64::consts::PI;
    }
    reference + wrap(angle - reference)
}

/// Wrap an angle difference into (−π, π].
pub fn wrap(delta: f64) -> f64 {
    use std::f64::consts::{PI, TAU};
    let mut d = delta.rem_euclid(TAU);
    if d > PI {
        d -= TAU;
    }
    d
}

/// Distance from a point to the segment `a`–`b` (3-D).
pub fn distance_to_segment(p: [f64; 3], a: [f64; 3], b: [f64; 3]) -> f64 {
    let ab = [b[0] - a[0], b[1] - a[1], b[2] - a[2]];
    let ap = [p[0] - a[0], p[1] - a[1], p[2] - a[2]];
    let len2 = ab[0] * ab[0] + ab[1] * ab[1] + ab[2] * ab[2];
    let t = if len2 == 0.0 {
        0.0
    } else {
        ((ap[0] * ab[0] + ap[1] * ab[1] + ap[2] * ab[2]) / len2).clamp(0.0, 1.0)
    };
    dist3(p, [a[0] + ab[0] * t, a[1] + ab[1] * t, a[2] + ab[2] * t])
}

/// Largest distance from the commanded segment of the joint-space chord between two nodes,
/// sampled at a quarter, half and three quarters.
pub fn chord_error(q0: Joints, q1: Joints, a: [f64; 3], b: [f64; 3]) -> f64 {
    [0.25, 0.5, 0.75]
        .iter()
        .map(|&f| {
            let q = [
                q0[0] + (q1[0] - q0[0]) * f,
                q0[1] + (q1[1] - q0[1]) * f,
                q0[2] + (q1[2] - q0[2]) * f,
            ];
            distance_to_segment(forward(q), a, b)
        })
        .fold(0.0, f64::max)
}

/// A rigorous bound on the distance between a joint-space chord and the Cartesian segment
/// joining its ends: with r and θ linear along the chord, `p(λ) = r(λ)·(cos θ, sin θ)` has
/// `|p''| ≤ 2|Δr·Δθ| + |r|max·Δθ²`, and a curve strays from its chord by at most `max|p''|/8`.
/// No trigonometry, so subdivision is cheap.
pub fn chord_error_bound(q0: Joints, q1: Joints) -> f64 {
    let dtheta = (q1[0] - q0[0]).abs();
    let dr = (q1[1] - q0[1]).abs();
    let r_max = q0[1].abs().max(q1[1].abs());
    (2.0 * dr * dtheta + r_max * dtheta * dtheta) / 8.0
}

/// Path lengths of the nodes that split `line` so every joint-space chord stays within
/// `tolerance` of the commanded segment (by [`chord_error_bound`], with 5 % margin for
/// rounding), and no two nodes are more than `max_spacing` apart. Always includes 0 and the
/// length.
pub fn subdivide(line: &Line, tolerance: f64, max_spacing: f64, out: &mut Vec<f64>) {
    let length = line.length();
    out.clear();
    let pieces = if max_spacing > 0.0 {
        (length / max_spacing).ceil().max(1.0) as usize
    } else {
        1
    };
    out.push(0.0);
    let mut previous = line.node(0.0).q;
    for k in 1..=pieces {
        let s1 = length * k as f64 / pieces as f64;
        let s0 = length * (k - 1) as f64 / pieces as f64;
        let q1 = line.node(s1).q;
        if !line.radial {
            refine(line, s0, previous, s1, q1, tolerance, out, 0);
        }
        out.push(s1);
        previous = q1;
    }
}

#[allow(clippy::too_many_arguments)]
fn refine(
    line: &Line,
    s0: f64,
    q0: Joints,
    s1: f64,
    q1: Joints,
    tolerance: f64,
    out: &mut Vec<f64>,
    depth: u32,
) {
    if depth > 40 || chord_error_bound(q0, q1) <= 0.95 * tolerance {
        return;
    }
    let sm = 0.5 * (s0 + s1);
    let qm = line.node(sm).q;
    refine(line, s0, q0, sm, qm, tolerance, out, depth + 1);
    out.push(sm);
    refine(line, sm, qm, s1, q1, tolerance, out, depth + 1);
}

#[cfg(test)]
mod tests {
    use super::*;

    fn general(a: [f64; 3], b: [f64; 3]) -> Line {
        Line {
            a,
            b,
            q_a: [a[1].atan2(a[0]), a[0].hypot(a[1]), a[2]],
            sign: 1.0,
            radial: false,
        }
    }

    /// Derivatives against central finite differences.
    #[test]
    fn analytic_derivatives_match_finite_differences() {
        for line in [
            general([0.03, -0.01, 0.0], [-0.02, 0.025, 0.004]),
            general([0.001, 0.0005, 0.0], [-0.001, 0.0007, 0.0]),
        ] {
            let l = line.length();
            for k in 1..10 {
                let s = l * k as f64 / 10.0;
                let h = l * 1e-5;
                let n = line.node(s);
                let (m, p) = (line.node(s - h), line.node(s + h));
                for j in 0..3 {
                    let d = (p.q[j] - m.q[j]) / (2.0 * h);
                    let dd = (p.q[j] - 2.0 * n.q[j] + m.q[j]) / (h * h);
                    assert!(
                        (d - n.dq[j]).abs() <= 1e-6 * (1.0 + d.abs()),
                        "dq{j}: {d} vs {}",
                        n.dq[j]
                    );
                    assert!(
                        (dd - n.ddq[j]).abs() <= 1e-3 * (1.0 + dd.abs()),
                        "ddq{j}: {dd} vs {}",
                        n.ddq[j]
                    );
                }
                // Joints map back onto the line.
                assert!(dist3(forward(n.q), line.point(s)) < 1e-15);
            }
        }
    }

    #[test]
    fn theta_is_continuous_across_the_seam_and_many_turns() {
        // Moving +y at x < 0 crosses the ±π seam: θ keeps decreasing past −π, ten turns up.
        let (a, b) = ([-0.02, -0.001, 0.0], [-0.02, 0.001, 0.0]);
        let turns = 10.0 * std::f64::consts::TAU;
        let theta_a = continuous_theta(a[0], a[1], turns, 1.0);
        assert!((theta_a - (turns - std::f64::consts::PI + (0.001f64).atan2(0.02))).abs() < 1e-12);
        let line = Line {
            a,
            b,
            q_a: [theta_a, 0.02f64.hypot(0.001), 0.0],
            sign: 1.0,
            radial: false,
        };
        let q_b = line.q_b();
        assert!((q_b[0] - theta_a + 2.0 * (0.001f64).atan2(0.02)).abs() < 1e-12);
        assert!(dist3(forward(q_b), b) < 1e-15);
    }

    /// The bound is never below the error measured by dense sampling.
    #[test]
    fn chord_bound_covers_the_sampled_error() {
        let line = general([0.004, -0.003, 0.0], [-0.001, 0.005, 0.0]);
        let l = line.length();
        for k in 0..50 {
            let (s0, s1) = (l * k as f64 / 50.0, l * (k + 1) as f64 / 50.0);
            for s1 in [s1, (s0 + 3.0 * s1) / 4.0, l] {
                let (q0, q1) = (line.node(s0).q, line.node(s1).q);
                let (a, b) = (line.point(s0), line.point(s1));
                let sampled = (0..=200)
                    .map(|i| {
                        let f = i as f64 / 200.0;
                        let q = [
                            q0[0] + (q1[0] - q0[0]) * f,
                            q0[1] + (q1[1] - q0[1]) * f,
                            0.0,
                        ];
                        distance_to_segment(forward(q), a, b)
                    })
                    .fold(0.0, f64::max);
                assert!(
                    chord_error_bound(q0, q1) >= sampled * (1.0 - 1e-9),
                    "{s0} {s1}"
                );
            }
        }
    }

    #[test]
    fn subdivision_keeps_chords_within_tolerance() {
        let line = general([0.05, -0.0002, 0.0], [-0.05, 0.0003, 0.0]);
        let mut nodes = Vec::new();
        subdivide(&line, 5e-6, 0.0, &mut nodes);
        assert!(nodes.len() > 10);
        for w in nodes.windows(2) {
            let (q0, q1) = (line.node(w[0]).q, line.node(w[1]).q);
            // Dense independent sampling of the chord.
            for k in 0..=100 {
                let f = k as f64 / 100.0;
                let q = [
                    q0[0] + (q1[0] - q0[0]) * f,
                    q0[1] + (q1[1] - q0[1]) * f,
                    0.0,
                ];
                assert!(distance_to_segment(forward(q), line.a, line.b) <= 5e-6);
            }
        }
    }
}
