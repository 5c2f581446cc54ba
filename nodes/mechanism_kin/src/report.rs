//! One tool-pose request evaluated end to end: the solution, every URDF joint and the checks
//! the node reports as diagnostics. Shared by the node and the CLI.

use crate::error::KinError;
use crate::geometry::Geometry;
use crate::kinematics::{ForwardSolver, JointPositions, ToolSolution, ToolTarget};
use crate::urdf::{joint_values_si, UrdfTree};

/// A solved tool pose with its self-checks.
#[derive(Debug, Clone, PartialEq)]
pub struct Evaluation {
    pub solution: ToolSolution,
    pub joints: JointPositions,
    /// Joint values in URDF units, in [`crate::urdf::joint_names`] order.
    pub joint_values_si: Vec<f64>,
    /// Newton iterations of the FK check.
    pub fk_iterations: u32,
    /// Tool-tip distance between the target and FK of the commanded legs and table, mm.
    pub fk_residual_mm: f64,
    /// Loop closure of the URDF tree with these joints, m.
    pub loop_closure_residual_m: f64,
    /// The seed's input/output ratio (eq. 4.22).
    pub io_ratio: f64,
    /// Smallest distance of a leg from its stroke ends, mm.
    pub leg_margin_mm: f64,
    /// Smallest spherical-joint swing reserve, rad.
    pub swing_margin_rad: f64,
    /// Smallest table reserve, mm.
    pub table_margin_mm: f64,
}

/// Solve `target` and check the answer by FK and through the URDF tree.
pub fn evaluate(
    geom: &Geometry,
    tree: &UrdfTree,
    fk: &mut ForwardSolver,
    target: &ToolTarget,
) -> Result<Evaluation, KinError> {
    let solution = geom.inverse_tool(target)?;
    check(geom, tree, fk, target, solution)
}

/// The checks of [`evaluate`] for a target already solved (e.g. by the CL post-processor).
pub fn check(
    geom: &Geometry,
    tree: &UrdfTree,
    fk: &mut ForwardSolver,
    target: &ToolTarget,
    solution: ToolSolution,
) -> Result<Evaluation, KinError> {
    let ik = &solution.ik;
    let joints = geom.joint_positions(ik, solution.table_mm);
    let joint_values_si = joint_values_si(&joints);
    let forward = fk.solve(geom, ik.legs_mm)?;
    let tip = forward.tool_tip_mm(geom)
        - nalgebra::Vector3::new(solution.table_mm[0], solution.table_mm[1], 0.0);
    let l = &geom.limits;
    let leg_margin_mm = ik
        .legs_mm
        .iter()
        .map(|&x| (x - l.leg_min_mm).min(l.leg_max_mm - x))
        .fold(f64::INFINITY, f64::min);
    let swing_margin_rad = geom
        .swing_rad(ik)
        .iter()
        .map(|s| l.swing_max_rad - s)
        .fold(f64::INFINITY, f64::min);
    let table_margin_mm = solution
        .table_mm
        .iter()
        .map(|t| l.table_max_mm - t.abs())
        .fold(f64::INFINITY, f64::min);
    Ok(Evaluation {
        joints,
        fk_iterations: forward.iterations,
        fk_residual_mm: (tip - target.tip_mm).norm(),
        loop_closure_residual_m: tree.loop_closure_residual_m(geom, &joint_values_si),
        io_ratio: geom.io_ratio(&ik.pose)?,
        joint_values_si,
        leg_margin_mm,
        swing_margin_rad,
        table_margin_mm,
        solution,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn evaluation_checks_close() {
        let (tree, geom) = crate::urdf::load(crate::BUILTIN_URDF).unwrap();
        let mut fk = ForwardSolver::default();
        let target = ToolTarget {
            tip_mm: nalgebra::Vector3::new(5.0, -3.0, 240.0),
            axis: nalgebra::Vector3::new(0.1, 0.2, 1.0).normalize(),
        };
        let e = evaluate(&geom, &tree, &mut fk, &target).unwrap();
        assert!(e.fk_residual_mm < 1e-9, "{}", e.fk_residual_mm);
        assert!(
            e.loop_closure_residual_m < 1e-12,
            "{}",
            e.loop_closure_residual_m
        );
        assert!(e.leg_margin_mm > 0.0 && e.swing_margin_rad > 0.0 && e.table_margin_mm > 0.0);
        assert_eq!(e.joint_values_si.len(), crate::urdf::joint_names().len());
    }
}
