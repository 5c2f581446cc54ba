//! `mechanism_kin [--ros-args ...]`: the mechanism kinematics node as its own process.

#[tokio::main]
async fn main() -> anyhow::Result<()> {
    cell_runtime::init_logging("info");
    mechanism_kin::node::main_with_args(std::env::args().skip(1).collect()).await
}
