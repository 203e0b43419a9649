//! `worldpack`: the product's command line.

mod bench;
mod demo;
mod geometry;

use std::io::Read;
use std::process::ExitCode;

use clap::{Parser, Subcommand};

#[derive(Parser)]
#[command(name = "worldpack", version, about = "Geometry-first memory for long-context video world models")]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Run every context policy over a built-in ABA loop and compare what they retrieve.
    Demo {
        /// Distance from A to B in blocks.
        #[arg(long, default_value_t = 15, value_parser = clap::value_parser!(u32).range(1..=500))]
        range: u32,
    },
    /// Benchmarks (tables on stdout; --json for machines).
    Bench {
        #[command(subcommand)]
        what: BenchCommand,
    },
    /// Answer geometry requests: JSON on stdin (one object or an array), JSON on stdout.
    ///
    /// Ops: convert, project, resize, frustum, overlap, select. See docs/cli.md.
    Geometry {
        /// Read the request from this file instead of stdin.
        #[arg(long)]
        input: Option<std::path::PathBuf>,
    },
}

#[derive(Subcommand)]
enum BenchCommand {
    /// Selection latency against stored frames: indexed exact, brute-force exact, brute-force Monte Carlo.
    Select {
        /// Comma-separated history sizes.
        #[arg(long, value_delimiter = ',', default_value = "50,100,400,1600,10000,100000")]
        candidates: Vec<usize>,
        #[arg(long, value_enum, default_value = "walk")]
        workload: bench::Workload,
        /// Target poses per size (each timed once for the indexed path).
        #[arg(long, default_value_t = 30, value_parser = clap::value_parser!(u64).range(1..=10_000))]
        queries: u64,
        /// Print JSON instead of a table.
        #[arg(long)]
        json: bool,
    },
}

fn main() -> ExitCode {
    match Cli::parse().command {
        Command::Demo { range } => {
            let rows = demo::run(range);
            demo::print(range, &rows);
            ExitCode::SUCCESS
        }
        Command::Bench { what: BenchCommand::Select { candidates, workload, queries, json } } => {
            if let Some(bad) = candidates.iter().find(|&&n| n == 0 || n > 2_000_000) {
                eprintln!("worldpack bench select: --candidates must lie in 1..=2000000, got {bad}");
                return ExitCode::from(2);
            }
            let rows = bench::run(workload, &candidates, queries as usize, true);
            if json {
                let out = serde_json::json!({ "workload": format!("{workload:?}").to_lowercase(), "rows": rows,
                    "loglog_slope": (rows.len() >= 2).then(|| bench::loglog_slope(&rows)) });
                println!("{out}");
            } else {
                bench::print(workload, &rows);
            }
            ExitCode::SUCCESS
        }
        Command::Geometry { input } => {
            let text = match input {
                Some(path) => std::fs::read_to_string(&path).map_err(|e| format!("cannot read {}: {e}", path.display())),
                None => {
                    let mut s = String::new();
                    std::io::stdin().read_to_string(&mut s).map(|_| s).map_err(|e| format!("cannot read stdin: {e}"))
                }
            };
            match text.and_then(|t| geometry::run(&t)) {
                Ok((out, all_ok)) => {
                    println!("{out}");
                    if all_ok { ExitCode::SUCCESS } else { ExitCode::from(2) }
                }
                Err(message) => {
                    eprintln!("worldpack geometry: {message}");
                    ExitCode::from(2)
                }
            }
        }
    }
}
