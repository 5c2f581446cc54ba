//! `gcode_streamer FILE.gcode [--ros-args ...]`: the streamer as its own process.

#[tokio::main]
async fn main() -> anyhow::Result<()> {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| {
                "info,rustdds=error,rustdds::network::udp_listener=off,ros2_client=error".into()
            }),
        )
        .with_writer(std::io::stderr)
        .init();
    gcode_streamer::node::main_with_args(std::env::args().skip(1).collect()).await
}
