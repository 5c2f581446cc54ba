//! Control points for linear leg interpolation: the seed's Fig. 4.4 sweep, and how many points
//! adaptive and uniform placement need for a path tolerance.
//!
//! `cargo run --release -p mechanism_kin --example path_points`

use mechanism_kin::path::{fig_4_4_path, IdealPath, PathGenerator, PathOptions, Straight};
use mechanism_kin::Pose;

fn main() -> Result<(), mechanism_kin::KinError> {
    let geom = mechanism_kin::Geometry::default();
    let mut gen = PathGenerator::new(&geom, PathOptions::default())?;
    let fig = fig_4_4_path();
    println!("Fig. 4.4: Z = 393 mm, θ1 = 0, θ2 −20° → +20° in 5° steps, output point");
    println!("  segment        max Z error (mm)");
    for k in 0..8 {
        let e = gen.segment_error(&fig, k as f64 / 8.0, (k + 1) as f64 / 8.0)?;
        println!(
            "  {:>4}° → {:>3}°  {:.4}",
            -20 + 5 * k,
            -15 + 5 * k,
            e.max_z_mm
        );
    }
    // A machining-like move: the tool tip descends 100 mm at a 5° tilt, then the platform
    // swings to 20° in another direction (ideal path: straight in (Z, w) per leg of the move).
    let a = Pose::from_theta(456.0, 60f64.to_radians(), 5f64.to_radians());
    let b = Pose::from_theta(356.0, 60f64.to_radians(), 5f64.to_radians());
    let c = Pose::from_theta(356.0, 150f64.to_radians(), 20f64.to_radians());
    let descend_then_swing = move |s: f64| {
        if s < 0.5 {
            a.lerp(&b, 2.0 * s)
        } else {
            b.lerp(&c, 2.0 * s - 1.0)
        }
    };
    let paths: [(&str, &dyn IdealPath); 3] = [
        ("Fig. 4.4 sweep", &fig),
        ("descend 100 mm, then swing to 20°", &descend_then_swing),
        (
            "tilt 0° → 20° at θ1 = 45°, Z 350",
            &Straight(
                Pose::from_theta(350.0, 45f64.to_radians(), 0.0),
                Pose::from_theta(350.0, 45f64.to_radians(), 20f64.to_radians()),
            ),
        ),
    ];
    for tol in [1e-3, 1e-4] {
        println!("\ntolerance {} µm", tol * 1e3);
        println!("  path                                  adaptive  uniform  ratio");
        for (name, path) in paths {
            let mut gen = PathGenerator::new(
                &geom,
                PathOptions {
                    tolerance_mm: tol,
                    ..PathOptions::default()
                },
            )?;
            let adaptive = gen.adaptive(path)?.len();
            let uniform = gen.uniform_segments_needed(path)? + 1;
            println!(
                "  {name:<38}{adaptive:>8} {uniform:>8}  {:.2}",
                adaptive as f64 / uniform as f64
            );
        }
    }
    Ok(())
}
