//! `gcode_streamer FILE.gcode [--ros-args ...]`: the streamer as its own process.

#[tokio::main]
async fn main() -> anyhow::Result<()> {
    cell_runtime::init_logging("info");
    gcode_streamer::node::main_with_args(std::env::args().skip(1).collect()).await
}
