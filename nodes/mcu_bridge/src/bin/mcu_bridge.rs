//! `mcu_bridge [--ros-args ... -p device:=PATH]`: the bridge to the cell's MCU as its own
//! process.

#[tokio::main]
async fn main() -> anyhow::Result<()> {
    cell_runtime::init_logging("info");
    mcu_bridge::node::main_with_args(std::env::args().skip(1).collect()).await
}
