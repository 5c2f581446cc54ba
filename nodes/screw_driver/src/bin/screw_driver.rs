//! `screw_driver [--ros-args ...]`: the screw driver as its own process.

#[tokio::main]
async fn main() -> anyhow::Result<()> {
    cell_runtime::init_logging("info");
    screw_driver::node::main_with_args(std::env::args().skip(1).collect()).await
}
