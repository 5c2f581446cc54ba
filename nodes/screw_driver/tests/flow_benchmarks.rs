//! The Navier–Stokes solver against the published lid-driven cavity benchmark of Ghia, Ghia &
//! Shin (1982) on their own 129×129-point grid (128×128 cells): every tabulated centreline
//! velocity within 1 % of the lid speed, at Re = 100 and Re = 1000.
use screw_driver::flow::ghia;

fn check(reynolds: u32) {
    let flow = ghia::solve_cavity(reynolds as f64, 128).expect("cavity");
    assert!(
        flow.rate_of_change() < 1e-6,
        "not steady: {}",
        flow.rate_of_change()
    );
    assert!(flow.max_divergence() < 1e-8, "{}", flow.max_divergence());
    let (du, dv) = ghia::compare(&flow, reynolds).unwrap();
    println!("Re {reynolds}: max |u − Ghia| {du:.5}, max |v − Ghia| {dv:.5}");
    assert!(du < 0.01 && dv < 0.01, "Re {reynolds}: u {du}, v {dv}");
}

#[test]
fn lid_driven_cavity_re_100_matches_ghia() {
    check(100);
}

#[test]
fn lid_driven_cavity_re_1000_matches_ghia() {
    check(1000);
}
