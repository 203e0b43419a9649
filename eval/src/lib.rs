//! Measuring WorldPack: image metrics, trajectory-level bootstrap
//! intervals, the depth-reprojection reference, suite reading, and the
//! teacher-forced memory probe (see docs/probe.md).

pub mod aba_demo;
pub mod digest;
pub mod evaluate;
pub mod features;
pub mod geometry_requests;
pub mod memory_probe;
pub mod metrics;
pub mod noise;
pub mod probe;
pub mod program;
pub mod reproject;
pub mod rollout;
pub mod stats;
pub mod strip;
pub mod strata;
pub mod study;
pub mod summary;
pub mod suite;
