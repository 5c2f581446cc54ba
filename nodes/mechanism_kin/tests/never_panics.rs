//! Whatever comes in, the kinematics answer with finite numbers or an error: no panic, no NaN.

use mechanism_kin::kinematics::{ForwardSolver, ToolTarget};
use mechanism_kin::{Geometry, Pose, Tilt};
use nalgebra::Vector3;
use proptest::prelude::*;

fn any_f64() -> impl Strategy<Value = f64> {
    prop_oneof![
        8 => -2000.0..2000.0f64,
        1 => Just(f64::NAN),
        1 => Just(f64::INFINITY),
        1 => Just(0.0),
        1 => -1e300..1e300f64,
    ]
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(2000))]

    #[test]
    fn inverse_is_finite_or_an_error(z in any_f64(), wx in -4.0..4.0f64, wy in -4.0..4.0f64) {
        let g = Geometry::default();
        let pose = Pose { z_mm: z, tilt: Tilt { wx_rad: wx, wy_rad: wy } };
        if let Ok(sol) = g.inverse(&pose) {
            prop_assert!(sol.legs_mm.iter().all(|l| l.is_finite()));
            let j = g.joint_positions(&sol, [0.0, 0.0]);
            prop_assert!(j.hinge_rad.iter().chain(j.sphere_rad.iter().flatten()).all(|v| v.is_finite()));
        }
        if let Ok(j) = g.jacobian(&pose) {
            prop_assert!(j.pose_by_legs.iter().all(|v| v.is_finite()));
        }
    }

    #[test]
    fn forward_is_finite_or_an_error(l1 in any_f64(), l2 in any_f64(), l3 in any_f64(), warm in any::<bool>()) {
        let g = Geometry::default();
        let mut fk = ForwardSolver::default();
        if warm {
            let _ = fk.solve(&g, [393.25, 393.25, 393.25]);
        }
        for solve in [ForwardSolver::solve, ForwardSolver::solve_unchecked] {
            if let Ok(sol) = solve(&mut fk, &g, [l1, l2, l3]) {
                prop_assert!(sol.pose.z_mm.is_finite() && sol.pose.tilt.wx_rad.is_finite() && sol.pose.tilt.wy_rad.is_finite());
                prop_assert!(sol.output_point_mm.iter().all(|v| v.is_finite()));
            }
        }
    }

    #[test]
    fn tool_targets_are_finite_or_an_error(x in any_f64(), y in any_f64(), z in any_f64(),
                                           ax in any_f64(), ay in any_f64(), az in any_f64()) {
        let g = Geometry::default();
        let target = ToolTarget { tip_mm: Vector3::new(x, y, z), axis: Vector3::new(ax, ay, az) };
        if let Ok(sol) = g.inverse_tool(&target) {
            prop_assert!(sol.ik.legs_mm.iter().chain(&sol.table_mm).all(|v| v.is_finite()));
        }
    }
}

fn cl_like_text() -> impl Strategy<Value = String> {
    // Lines mixing valid rows, near-misses and junk.
    let line = prop_oneof![
        Just("0,0,250,0,0,-1,s".to_string()),
        Just("1.5,-2,251,0,0.0871557427,-0.9961946981,w".to_string()),
        Just("0,0,250,0,0,-1,e".to_string()),
        Just("Px,Py,Pz,Vx,Vy,Vz,flag".to_string()),
        Just("# comment".to_string()),
        Just(String::new()),
        "[-0-9.,eswq ]{0,40}",
        "\\PC{0,30}",
    ];
    prop::collection::vec(line, 0..12).prop_map(|l| l.join("\n"))
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(3000))]

    #[test]
    fn cl_parser_never_panics_and_names_a_real_line(text in cl_like_text()) {
        let opts = mechanism_kin::cl::PostOptions::default();
        match mechanism_kin::cl::parse("f.cl", &text, &opts) {
            Ok(points) => {
                prop_assert!(!points.is_empty());
                let g = Geometry::default();
                let _ = mechanism_kin::cl::post_process("f.cl", &g, &points, &opts);
            }
            Err(mechanism_kin::cl::ClError::Malformed { line, .. }) => {
                prop_assert!(line >= 1 && line <= text.lines().count().max(1));
            }
            Err(other) => prop_assert!(false, "{other}"),
        }
    }

    #[test]
    fn measurement_parser_never_panics(text in "\\PC{0,200}", header in any::<bool>()) {
        let text = if header {
            format!("{}\n{text}", mechanism_kin::calib::measurements::HEADER)
        } else {
            text
        };
        if let Err(mechanism_kin::calib::CalibError::Malformed { line, .. }) =
            mechanism_kin::calib::measurements::parse("m.csv", &text)
        {
            prop_assert!(line >= 1 && line <= text.lines().count().max(1));
        }
    }
}
