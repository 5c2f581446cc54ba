//! The calibration study (issue 6): simulated machines with uniform errors of ±0.5 mm / ±0.5°
//! on all 38 parameters (the seed's setting, ch. 5.4.1.2), measured with Gaussian noise of
//! σ = 1 µm per coordinate and σ = 1″ per axis component, calibrated by the response surface
//! (seed ch. 6) and by geometric identification, validated on 300 poses the calibration never
//! saw: inside the response surface's region and across the whole work range.
//!
//! `cargo run --release -p mechanism_kin --example calibration_study`

use mechanism_kin::calib::geometric::{measurement_plan, IdentifyOptions};
use mechanism_kin::calib::rsm::{d_optimal_design, Region};
use mechanism_kin::calib::simulate::{
    random_target, validate, validate_with, Simulation, ValidationErrors,
};
use mechanism_kin::calib::{calibrate, Calibration, Method};
use mechanism_kin::kinematics::ToolTarget;
use mechanism_kin::{Geometry, Tilt};
use nalgebra::Vector3;
use rand::{Rng, SeedableRng};

const MACHINES: u64 = 10;

fn region_targets(region: &Region, n: usize) -> Vec<ToolTarget> {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(4242);
    (0..n)
        .map(|_| {
            let z = rng.random_range(region.tip_z_mm[0]..=region.tip_z_mm[1]);
            let t1 = rng.random_range(region.theta1_deg[0]..=region.theta1_deg[1]);
            let t2 = rng.random_range(region.theta2_deg[0]..=region.theta2_deg[1]);
            ToolTarget {
                tip_mm: Vector3::new(0.0, 0.0, z),
                axis: Tilt::from_theta(t1.to_radians(), t2.to_radians()).normal(),
            }
        })
        .collect()
}

fn arcsec(rad: f64) -> f64 {
    rad.to_degrees() * 3600.0
}

/// Worst max and mean RMS over the machines.
fn row(errors: &[ValidationErrors]) -> String {
    let max_tip = errors.iter().map(|e| e.max_tip_mm).fold(0.0, f64::max);
    let max_axis = errors.iter().map(|e| e.max_axis_rad).fold(0.0, f64::max);
    let rms_tip = errors.iter().map(|e| e.rms_tip_mm).sum::<f64>() / errors.len() as f64;
    let rms_axis = errors.iter().map(|e| e.rms_axis_rad).sum::<f64>() / errors.len() as f64;
    let refused: usize = errors.iter().map(|e| e.refused).sum();
    format!(
        "{:>10.2} {:>9.2} {:>10.2} {:>9.2} {:>8}",
        max_tip * 1e3,
        arcsec(max_axis),
        rms_tip * 1e3,
        arcsec(rms_axis),
        refused
    )
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let geom = Geometry::default();
    let region = Region::default();
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(999);
    let work: Vec<ToolTarget> = (0..300).map(|_| random_target(&mut rng, &geom)).collect();
    let inside = region_targets(&region, 300);
    let noise_tip = 1e-3;
    let noise_axis = (1.0f64 / 3600.0).to_radians();
    println!(
        "{MACHINES} machines, errors ±0.5 mm / ±0.5° on all 38 parameters, noise σ 1 µm / 1″; \
         errors at 300 validation poses (worst machine for max, mean over machines for RMS)"
    );
    println!(
        "RSM region: tip Z {:?} mm, θ1 {:?}°, θ2 {:?}°\n",
        region.tip_z_mm, region.theta1_deg, region.theta2_deg
    );
    println!(
        "{:<44} {:>5} {:>10} {:>9} {:>10} {:>9} {:>8}",
        "method / validated on", "poses", "max µm", "max ″", "rms µm", "rms ″", "refused"
    );
    let uncalibrated = |targets: &[ToolTarget]| -> Vec<ValidationErrors> {
        (1..=MACHINES)
            .map(|seed| {
                let sim =
                    Simulation::new(&geom, seed, 0.5, 0.5f64.to_radians(), noise_tip, noise_axis)
                        .expect("valid study settings");
                validate(&geom, &sim.truth, None, targets)
            })
            .collect()
    };
    println!(
        "{:<44} {:>5} {}",
        "uncalibrated, work range",
        0,
        row(&uncalibrated(&work))
    );
    println!(
        "{:<44} {:>5} {}",
        "uncalibrated, RSM region",
        0,
        row(&uncalibrated(&inside))
    );
    for poses in [10, 15, 20, 30, 40] {
        let mut geo_work = Vec::new();
        let mut geo_inside = Vec::new();
        let mut rsm_inside = Vec::new();
        let mut rsm_outside = Vec::new();
        let plan = measurement_plan(&geom, poses, &IdentifyOptions::default())?;
        let design = if poses > 10 {
            Some(d_optimal_design(&geom, &region, poses)?.0)
        } else {
            None
        };
        for seed in 1..=MACHINES {
            let mut sim =
                Simulation::new(&geom, seed, 0.5, 0.5f64.to_radians(), noise_tip, noise_axis)?;
            let data = sim.measure_legs(&plan)?;
            let cal = calibrate(&geom, &data, Method::Geometric)?;
            geo_work.push(validate(&geom, &sim.truth, Some(&cal), &work));
            geo_inside.push(validate(&geom, &sim.truth, Some(&cal), &inside));
            if let Some(design) = &design {
                let data = sim.measure_legs(design)?;
                let cal = calibrate(&geom, &data, Method::Rsm)?;
                rsm_inside.push(validate(&geom, &sim.truth, Some(&cal), &inside));
                let Calibration::Rsm { surfaces, .. } = &cal else {
                    unreachable!()
                };
                rsm_outside.push(validate_with(&sim.truth, &work, |t| {
                    surfaces
                        .solve_unchecked(&geom, t)
                        .map(|c| (c.legs_mm, c.table_mm))
                }));
            }
        }
        println!(
            "{:<44} {:>5} {}",
            "geometric (LM), work range",
            poses,
            row(&geo_work)
        );
        println!(
            "{:<44} {:>5} {}",
            "geometric (LM), RSM region",
            poses,
            row(&geo_inside)
        );
        if !rsm_inside.is_empty() {
            println!(
                "{:<44} {:>5} {}",
                "response surface, its region",
                poses,
                row(&rsm_inside)
            );
            println!(
                "{:<44} {:>5} {}",
                "response surface, work range (extrapolated)",
                poses,
                row(&rsm_outside)
            );
        }
    }
    Ok(())
}
