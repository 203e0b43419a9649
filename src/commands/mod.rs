//! One module per `worldpack` subcommand: its arguments (clap) beside its
//! `run`. The work itself is in the library crates; these parse, call and print.

pub mod bench;
pub mod check;
pub mod condition_study;
pub mod demo;
pub mod fusion_data;
pub mod geometry;
pub mod plan;
pub mod rollout_eval;
pub mod serve;
pub mod sim;
pub mod teacher_probe;
pub mod train;
