//! Published reference: the lid-driven cavity centreline velocities of Ghia, Ghia & Shin,
//! "High-Re solutions for incompressible flow using the Navier–Stokes equations and a
//! multigrid method", J. Comput. Phys. 48 (1982) 387–411, Tables I and II (129×129 grid).
//! Unit cavity, lid u = 1 at y = 1.

/// y of Table I (u along the vertical line through the centre, x = 0.5).
pub const Y: [f64; 17] = [
    1.0000, 0.9766, 0.9688, 0.9609, 0.9531, 0.8516, 0.7344, 0.6172, 0.5000, 0.4531, 0.2813, 0.1719,
    0.1016, 0.0703, 0.0625, 0.0547, 0.0000,
];

/// x of Table II (v along the horizontal line through the centre, y = 0.5).
pub const X: [f64; 17] = [
    1.0000, 0.9688, 0.9609, 0.9531, 0.9453, 0.9063, 0.8594, 0.8047, 0.5000, 0.2344, 0.2266, 0.1563,
    0.0938, 0.0781, 0.0703, 0.0625, 0.0000,
];

/// Table I, Re = 100.
pub const U_RE100: [f64; 17] = [
    1.00000, 0.84123, 0.78871, 0.73722, 0.68717, 0.23151, 0.00332, -0.13641, -0.20581, -0.21090,
    -0.15662, -0.10150, -0.06434, -0.04775, -0.04192, -0.03717, 0.00000,
];

/// Table I, Re = 1000.
pub const U_RE1000: [f64; 17] = [
    1.00000, 0.65928, 0.57492, 0.51117, 0.46604, 0.33304, 0.18719, 0.05702, -0.06080, -0.10648,
    -0.27805, -0.38289, -0.29730, -0.22220, -0.20196, -0.18109, 0.00000,
];

/// Table II, Re = 100.
pub const V_RE100: [f64; 17] = [
    0.00000, -0.05906, -0.07391, -0.08864, -0.10313, -0.16914, -0.22445, -0.24533, 0.05454,
    0.17527, 0.17507, 0.16077, 0.12317, 0.10890, 0.10091, 0.09233, 0.00000,
];

/// Table II, Re = 1000.
pub const V_RE1000: [f64; 17] = [
    0.00000, -0.21388, -0.27669, -0.33714, -0.39188, -0.51550, -0.42665, -0.31966, 0.02526,
    0.32235, 0.33075, 0.37095, 0.32627, 0.30353, 0.29012, 0.27485, 0.00000,
];

/// The table columns for a Reynolds number the paper covers (100 or 1000).
pub fn tables(reynolds: u32) -> Option<(&'static [f64; 17], &'static [f64; 17])> {
    match reynolds {
        100 => Some((&U_RE100, &V_RE100)),
        1000 => Some((&U_RE1000, &V_RE1000)),
        _ => None,
    }
}

/// Largest |u − Ghia| and |v − Ghia| (in units of the lid speed) of a cavity flow solved at
/// `reynolds`, over the 17 + 17 table points.
pub fn compare(flow: &super::Flow, reynolds: u32) -> Option<(f64, f64)> {
    let (u_ref, v_ref) = tables(reynolds)?;
    let du = Y
        .iter()
        .zip(u_ref)
        .map(|(&y, &u)| (flow.u_velocity(0.5, y) - u).abs())
        .fold(0.0, f64::max);
    let dv = X
        .iter()
        .zip(v_ref)
        .map(|(&x, &v)| (flow.v_velocity(x, 0.5) - v).abs())
        .fold(0.0, f64::max);
    Some((du, dv))
}

/// The unit lid-driven cavity at `reynolds` on `cells`² cells, run to a steady state.
pub fn solve_cavity(reynolds: f64, cells: usize) -> Result<super::Flow, super::FlowError> {
    let mut flow = super::Flow::new(super::FlowOptions {
        cells_x: cells,
        cells_y: cells,
        kinematic_viscosity: 1.0 / reynolds,
        ..super::FlowOptions::default()
    })?;
    flow.run_to_steady(1e-6, 400.0)?;
    Ok(flow)
}
