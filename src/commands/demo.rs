//! `worldpack demo`: every context policy over a built-in ABA loop
//! (`eval::aba_demo`), printed as a table.

use eval::aba_demo::Row;

#[derive(clap::Args)]
pub struct Args {
    /// Distance from A to B in blocks.
    #[arg(long, default_value_t = 15, value_parser = clap::value_parser!(u32).range(1..=500))]
    range: u32,
}

pub fn run(a: &Args) -> anyhow::Result<()> {
    print(a.range, &eval::aba_demo::run(a.range));
    Ok(())
}

fn print(range: u32, rows: &[Row]) {
    println!("ABA loop, range {range} blocks, 70° FoV, far 30: context for each return-leg frame\n");
    println!("{:<24} {:>16} {:>20} {:>16}", "policy", "view covered", "from exploration", "select (µs)");
    for r in rows {
        println!(
            "{:<24} {:>15.1}% {:>19.1}% {:>16.1}",
            format!("{:?}", r.policy),
            100.0 * r.coverage,
            100.0 * r.from_exploration,
            r.median_us
        );
    }
    println!("\nview covered: share of the next frame's frustum inside at least one selected frame's frustum.");
    println!("from exploration: share of selected frames taken before the return leg began.");
}
