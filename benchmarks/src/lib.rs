//! The workloads and timing loops behind `worldpack bench`, with the tables
//! they print; the binary only parses flags and calls them.

pub mod fork;
pub mod imagine;
pub mod parity;
pub mod render;
pub mod select;
pub mod serve;
pub mod step;
pub mod store;
pub mod walk;
