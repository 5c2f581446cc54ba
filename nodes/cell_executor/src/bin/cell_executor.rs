//! `cell_executor [--ros-args ...]`: the executor as its own process.

#[tokio::main]
async fn main() -> anyhow::Result<()> {
    cell_runtime::init_logging("info");
    cell_executor::node::main_with_args(std::env::args().skip(1).collect()).await
}
