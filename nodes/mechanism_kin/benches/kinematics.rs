//! Per-solve cost of the mechanism's kinematics and of adaptive path generation.
//!
//! IK is timed on 1024 poses spread over the work range (cycled); warm FK follows a smooth
//! pose sequence (0.05° / 0.05 mm steps, as a controller does), cold FK starts every solve
//! from the flat-platform guess.

use criterion::{black_box, criterion_group, criterion_main, Criterion};
use mechanism_kin::kinematics::ForwardSolver;
use mechanism_kin::path::{fig_4_4_path, PathGenerator, PathOptions};
use mechanism_kin::{Geometry, Pose};

fn poses() -> Vec<Pose> {
    (0..1024)
        .map(|k| {
            let f = k as f64 / 1024.0;
            Pose::from_theta(
                256.0 + 200.0 * ((7.0 * f).fract()),
                (5.0 + 170.0 * ((13.0 * f).fract())).to_radians(),
                (-20.0 + 40.0 * ((29.0 * f).fract())).to_radians(),
            )
        })
        .collect()
}

fn smooth_legs(geom: &Geometry) -> Vec<[f64; 3]> {
    (0..1024)
        .map(|k| {
            let s = k as f64 * 0.05;
            geom.leg_lengths(&Pose::from_theta(
                350.0 + 0.05 * k as f64 * 0.2,
                (30.0 + s).to_radians(),
                (10.0 * (s / 20.0).sin()).to_radians(),
            ))
        })
        .collect()
}

fn kinematics(c: &mut Criterion) {
    let g = Geometry::default();
    let poses = poses();
    let mut i = 0;
    c.bench_function("ik_leg_lengths", |b| {
        b.iter(|| {
            i = (i + 1) & 1023;
            black_box(g.leg_lengths(black_box(&poses[i])))
        })
    });
    c.bench_function("ik_checked_with_joints", |b| {
        b.iter(|| {
            i = (i + 1) & 1023;
            let sol = g.inverse(black_box(&poses[i])).unwrap();
            black_box(g.joint_positions(&sol, [0.0, 0.0]))
        })
    });
    let legs: Vec<[f64; 3]> = poses.iter().map(|p| g.leg_lengths(p)).collect();
    let mut fk = ForwardSolver::default();
    c.bench_function("fk_cold", |b| {
        b.iter(|| {
            i = (i + 1) & 1023;
            fk.reset();
            black_box(fk.solve(&g, black_box(legs[i])).unwrap())
        })
    });
    let smooth = smooth_legs(&g);
    let mut fk = ForwardSolver::default();
    c.bench_function("fk_warm", |b| {
        b.iter(|| {
            i = (i + 1) & 1023;
            if i == 0 {
                fk.reset();
            }
            black_box(fk.solve(&g, black_box(smooth[i])).unwrap())
        })
    });
    c.bench_function("jacobian", |b| {
        b.iter(|| {
            i = (i + 1) & 1023;
            black_box(g.jacobian(black_box(&poses[i])).unwrap())
        })
    });
    let mut group = c.benchmark_group("path");
    group.sample_size(10);
    group.bench_function("adaptive_fig_4_4_1um", |b| {
        b.iter(|| {
            let mut gen = PathGenerator::new(&g, PathOptions::default()).unwrap();
            black_box(gen.adaptive(&fig_4_4_path()).unwrap())
        })
    });
    group.finish();
}

criterion_group!(benches, kinematics);
criterion_main!(benches);
