//! `worldpack train`: a dataset folder to a served model folder. The recipe is
//! PyTorch, so this hands the command to the trainer's package (`train/`,
//! `python -m worldpack_train make`) in its own venv, and gives it this binary
//! for the steps it needs from Rust (check, plan, eval).

use std::path::PathBuf;
use std::process::Command;

use anyhow::{Context, Result, bail};

/// The Python the trainer runs in: $WORLDPACK_TRAIN_PYTHON, or the venv `./scripts/train.sh` makes.
const PYTHON_ENV: &str = "WORLDPACK_TRAIN_PYTHON";
const VENV_PYTHON: &str = ".venv-train/bin/python";

#[derive(clap::Args)]
pub struct Args {
    /// A suite in the dataset format (docs/dataset.md); `worldpack check` must accept it.
    #[arg(long)]
    pub data: PathBuf,
    /// The model folder to write; run the same command again to resume it.
    #[arg(long)]
    pub out: PathBuf,
    /// Fine-tune from a shipped family (voxel, doom) or a folder this command wrote;
    /// without it, every stage trains from scratch.
    #[arg(long = "from")]
    pub from: Option<String>,
    /// The whole command's budget in hours, training to card (default 2).
    #[arg(long)]
    pub hours: Option<f64>,
    /// Where the training stages run: cpu or cuda (default cpu).
    #[arg(long, value_parser = ["cpu", "cuda"])]
    pub device: Option<String>,
    /// A suite to evaluate on instead of a held-out split of --data.
    #[arg(long)]
    pub heldout: Option<PathBuf>,
    /// Override a setting of train.json on a new run, e.g. `teacher.steps=500` (repeatable).
    #[arg(long = "set", value_name = "KEY=VALUE")]
    pub set: Vec<String>,
}

pub fn run(a: &Args) -> Result<()> {
    let python = std::env::var_os(PYTHON_ENV).map(PathBuf::from).unwrap_or_else(|| PathBuf::from(VENV_PYTHON));
    if !python.exists() {
        bail!("no trainer Python at {}: run ./scripts/train.sh (it makes the venv with torch), or set {PYTHON_ENV}", python.display());
    }
    let binary = std::env::current_exe().context("where this binary is")?;
    let mut cmd = Command::new(&python);
    cmd.args(["-m", "worldpack_train", "make", "--bin"]).arg(binary).arg("--data").arg(&a.data).arg("--out").arg(&a.out);
    if let Some(from) = &a.from {
        cmd.args(["--from", from]);
    }
    if let Some(hours) = a.hours {
        cmd.args(["--hours", &hours.to_string()]);
    }
    if let Some(device) = &a.device {
        cmd.args(["--device", device]);
    }
    if let Some(heldout) = &a.heldout {
        cmd.arg("--heldout").arg(heldout);
    }
    for pair in &a.set {
        cmd.args(["--set", pair]);
    }
    let status = cmd.status().with_context(|| format!("starting {}", python.display()))?;
    if !status.success() {
        // The trainer has printed which stage failed and what to do.
        bail!("the trainer stopped ({status})");
    }
    Ok(())
}
