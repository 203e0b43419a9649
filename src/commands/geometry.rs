//! `worldpack geometry`: JSON requests (`eval::geometry_requests`) on stdin, one
//! object or an array; the answers on stdout.

use std::io::Read;
use std::path::PathBuf;
use std::process::ExitCode;

use eval::geometry_requests::answer_all;

#[derive(clap::Args)]
pub struct Args {
    /// Read the request from this file instead of stdin.
    #[arg(long)]
    input: Option<PathBuf>,
}

/// Prints the answers; exit code 2 when any request failed.
pub fn run(a: &Args) -> ExitCode {
    let text = match &a.input {
        Some(path) => std::fs::read_to_string(path).map_err(|e| format!("cannot read {}: {e}", path.display())),
        None => {
            let mut s = String::new();
            std::io::stdin().read_to_string(&mut s).map(|_| s).map_err(|e| format!("cannot read stdin: {e}"))
        }
    };
    match text.and_then(|t| answer_all(&t)) {
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
