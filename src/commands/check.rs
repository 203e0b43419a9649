//! `worldpack check`: a suite folder against the dataset format (docs/dataset.md).

use std::path::PathBuf;

#[derive(clap::Args)]
pub struct Args {
    /// A suite folder (index.json and one folder per trajectory).
    #[arg(long)]
    data: PathBuf,
}

pub fn run(a: &Args) -> anyhow::Result<()> {
    let data = &a.data;
    let c = eval::suite::check(data)?;
    println!(
        "{}: {} trajectories, {} frames ({} on return legs), {}x{}, {}",
        data.display(),
        c.trajectories,
        c.frames,
        c.returning_frames,
        c.width,
        c.height,
        if c.without_depth == 0 { "depth in every trajectory".to_string() } else { format!("{} without depth", c.without_depth) }
    );
    Ok(())
}
