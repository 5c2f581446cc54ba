//! `polar_planner [--ros-args ...]`: the planner as its own process.

#[tokio::main]
async fn main() -> anyhow::Result<()> {
    cell_runtime::init_logging("info");
    polar_planner::node::main_with_args(std::env::args().skip(1).collect()).await
}
