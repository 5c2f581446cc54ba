//! `bag_recorder --ros-args -p output:=FILE.mcap`: the recorder as its own process.

#[tokio::main]
async fn main() -> anyhow::Result<()> {
    cell_runtime::init_logging("info");
    cell_bag::node::main_with_args(std::env::args().skip(1).collect()).await
}
