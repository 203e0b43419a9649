//! A LoopNav-style synthetic world that WorldPack owns: procedural voxel
//! terrain with biomes and landmarks ([`terrain`]), a ray-cast RGB + depth
//! renderer on the memory crate's OpenCV camera ([`mod@render`]), a
//! Minecraft-like player whose physics is also the motion model ([`agent`]),
//! LoopNav's ABA/ABCA protocol ([`trajectory`]), and suites on disk as NumPy
//! arrays ([`suite`], [`npy`]). See `docs/world.md`.

pub mod agent;
pub mod blocks;
pub mod noise;
pub mod npy;
pub mod picture;
pub mod render;
pub mod suite;
pub mod terrain;
pub mod trajectory;

pub use agent::{Action, PlayerState};
pub use render::{Frame, RenderSettings, render};
pub use terrain::{Biome, World};
pub use trajectory::{Phase, Task, Trajectory, TrajectorySpec};
