//! The `cell_executor` node: the virtual machine on the ROS graph.
//!
//! The [`crate::Executor`] is the machine; [`cell_machine::node`] gives it its ROS face
//! (topics, services, plan credit, diagnostics), the same one a microcontroller behind the
//! bridge has.

use cell_machine::node::{MachineParams, Request, Status};
use cell_runtime::{CellNode, ParamSpec, ParamValue};
use tokio::sync::{mpsc, watch};

use crate::session::{Executor, ExecutorOptions};
use crate::PlayerOptions;

/// Default node name.
pub const NODE_NAME: &str = "cell_executor";

/// The executor's default `tick_period_s`. The virtual machine needs no polling: its loop
/// wakes for commands, messages and the sample grid, and otherwise only to refresh the
/// credit and status, which are due every 50–100 ms.
pub const EXECUTOR_TICK_PERIOD_S: f64 = 0.02;

/// The machine node's parameters and the executor's own.
pub fn param_specs() -> Vec<ParamSpec> {
    let mut specs = cell_machine::node::param_specs(EXECUTOR_TICK_PERIOD_S);
    specs.push(
        ParamSpec::new(
            "control_period_s",
            ParamValue::Double(0.001),
            "period of the executor's clock (and of a feed hold's control)",
        )
        .range(1e-5, 0.1),
    );
    specs
}

/// The executor the parameters describe.
pub fn executor_from_params(params: &MachineParams, control_period_s: f64) -> ExecutorOptions {
    let mut player = PlayerOptions::new(
        params.steps.clone(),
        params.joint_accelerations,
        params.pin_open_delay_s,
    );
    player.control_period_s = control_period_s;
    player.queue_capacity = params.queue_capacity;
    player.initial_steps = params.initial_steps();
    // Held for an underrun, the machine gets at most the horizon ahead: resume within it.
    player.underrun_resume_s = (params.horizon_s / 4.0).min(0.5);
    ExecutorOptions::new(player, params.screw_hold)
}

/// Run the executor on `node` until an error. `commands` come from the same process (a
/// print's Ctrl-C); `status` tells it how the machine is doing.
pub async fn run(
    node: &mut CellNode,
    commands: mpsc::UnboundedReceiver<Request>,
    status: watch::Sender<Status>,
) -> anyhow::Result<()> {
    let params = MachineParams::from_params(&node.params)?;
    let options = executor_from_params(&params, node.params.f64("control_period_s"));
    let mut executor = Executor::new(options);
    cell_machine::node::run(node, &mut executor, &params, commands, status).await
}

/// Run the node from its own command line until SIGINT/SIGTERM.
pub async fn main_with_args(argv: Vec<String>) -> anyhow::Result<()> {
    cell_machine::node::main_with_args(NODE_NAME, &param_specs(), argv, |node, rx, tx| {
        Box::pin(run(node, rx, tx))
    })
    .await
}
