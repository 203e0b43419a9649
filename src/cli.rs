//! Argument pieces several commands share: value parsers and the runtime group.

use std::path::PathBuf;

use clap::builder::RangedU64ValueParser;

pub fn parse_provider(s: &str) -> Result<model::Provider, String> {
    s.parse()
}

pub fn parse_method(s: &str) -> Result<model::Method, String> {
    s.parse()
}

pub fn parse_named_path(s: &str) -> Result<(String, PathBuf), String> {
    match s.split_once('=') {
        Some((name, dir)) if !name.is_empty() && !dir.is_empty() => Ok((name.to_string(), PathBuf::from(dir))),
        _ => Err(format!("expected NAME=DIR, got {s:?}")),
    }
}

/// A whole number in `lo..=hi`, refused by clap with the flag's name otherwise.
pub fn count(lo: u64, hi: u64) -> RangedU64ValueParser<usize> {
    RangedU64ValueParser::<usize>::new().range(lo..=hi)
}

/// Where the analysis commands run their models.
#[derive(clap::Args, Clone, Copy, Debug)]
pub struct Runtime {
    #[arg(long, default_value = "cpu", value_parser = parse_provider)]
    pub provider: model::Provider,
    /// Intra-op threads per model session.
    #[arg(long, default_value_t = 2)]
    pub threads: usize,
}

impl Runtime {
    pub fn options(&self) -> model::RuntimeOptions {
        model::RuntimeOptions { provider: self.provider, threads: self.threads }
    }
}

/// A progress bar for `len` items of work called `what`.
pub fn bar(len: usize, what: &str) -> indicatif::ProgressBar {
    let bar = indicatif::ProgressBar::new(len as u64);
    bar.set_style(
        indicatif::ProgressStyle::with_template("{prefix} [{bar:30}] {pos}/{len} {msg} ({elapsed}, ~{eta} left)")
            .unwrap()
            .progress_chars("=> "),
    );
    bar.set_prefix(what.to_string());
    bar
}

/// Worker threads for work spread over every core.
pub fn threads() -> usize {
    std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1)
}
