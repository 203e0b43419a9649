//! `worldpack`: the product's command line.

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
    /// Answer geometry requests: JSON on stdin (one object or an array), JSON on stdout.
    ///
    /// Ops: convert, project, resize, frustum, overlap, select. See docs/cli.md.
    Geometry {
        /// Read the request from this file instead of stdin.
        #[arg(long)]
        input: Option<std::path::PathBuf>,
    },
}

fn main() -> ExitCode {
    match Cli::parse().command {
        Command::Demo { range } => {
            let rows = demo::run(range);
            demo::print(range, &rows);
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
