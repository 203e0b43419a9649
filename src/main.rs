//! `worldpack`: the product's command line. Each subcommand's arguments and
//! its `run` are in `commands/`; this file only names them.

mod cli;
mod commands;

use std::process::ExitCode;

use clap::{Parser, Subcommand};
use commands::{bench, check, condition_study, demo, fusion_data, geometry, plan, rollout_eval, serve, sim, teacher_probe, train};

#[derive(Parser)]
#[command(name = "worldpack", version, about = "Geometry-first memory for long-context video world models")]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Run every context policy over a built-in ABA loop and compare what they retrieve.
    Demo(demo::Args),
    /// Serve the REST API (sessions, step, observe, select) over the committed model and a local store.
    Serve(Box<serve::Args>),
    /// Benchmarks (tables on stdout; --json for machines).
    Bench {
        #[command(subcommand)]
        what: bench::Bench,
    },
    /// The synthetic LoopNav-style voxel world: suites, training data, single frames.
    Sim {
        #[command(subcommand)]
        what: sim::Sim,
    },
    /// The memory probe: teacher-forced next-frame prediction on a suite's return legs, for each trained
    /// variant, the WorldPack weights on recency contexts, and the copy and reproject references.
    Probe(teacher_probe::Options),
    /// Speed against accuracy, stability under pose noise and where methods
    /// fail (docs/cli.md; `./scripts/results.sh` with STUDY=1): the probe under many conditions, paired frame by frame.
    Study(condition_study::Options),
    /// LoopNav-style evaluation: observe each trajectory's exploration, roll out its return leg
    /// autoregressively under each policy with its own weights, and score PSNR and SSIM per frame.
    Eval(Box<rollout_eval::Options>),
    /// Training examples for a geometry model's fusion head: its own predictions, the fused
    /// reference of its warp sources, where the warp landed and the truth, on a suite's return legs.
    FusionData(fusion_data::Options),
    /// PSNR and SSIM of two PNG images, as JSON (the metrics `eval` uses).
    Compare(rollout_eval::CompareArgs),
    /// Write each trajectory's context plans (plan-<policy>.npy) beside a suite or dataset, for training.
    Plan(plan::Args),
    /// Check a suite folder against the dataset format (docs/dataset.md): every file and field
    /// that training, `plan` and `eval` read. Names the file and field of the first fault.
    Check(check::Args),
    /// A dataset folder to a served model folder with its card: every stage of the recipe, resumable
    /// (the trainer's package, train/; docs/training.md).
    Train(train::Args),
    /// Answer geometry requests: JSON on stdin (one object or an array), JSON on stdout.
    ///
    /// Ops: convert, project, resize, frustum, overlap, select. See docs/cli.md.
    Geometry(geometry::Args),
}

fn main() -> ExitCode {
    let (command, result) = match Cli::parse().command {
        Command::Demo(a) => ("demo", demo::run(&a)),
        Command::Serve(a) => ("serve", serve::run(*a)),
        Command::Bench { what } => (what.name(), what.run()),
        Command::Sim { what } => (what.name(), what.run()),
        Command::Probe(o) => ("probe", teacher_probe::run(&o)),
        Command::Study(o) => ("study", condition_study::run(&o)),
        Command::Eval(o) => ("eval", rollout_eval::run(&o)),
        Command::FusionData(o) => ("fusion-data", fusion_data::run(&o)),
        Command::Compare(a) => ("compare", rollout_eval::compare(&a)),
        Command::Plan(a) => ("plan", plan::run(&a)),
        Command::Check(a) => ("check", check::run(&a)),
        Command::Train(a) => ("train", train::run(&a)),
        Command::Geometry(a) => return geometry::run(&a),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            // The error chain as one line naming the command.
            eprintln!("worldpack {command}: {e:#}");
            ExitCode::from(2)
        }
    }
}
