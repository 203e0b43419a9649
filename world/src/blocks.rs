//! Block materials: colours and simple per-face textures, chosen so that
//! biomes and landmarks look different from each other at 64×64.

use crate::noise::unit;

/// One voxel. `Air` is empty; everything else stops rays and players
/// (water included: the player walks on it, but paths avoid it).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
#[repr(u8)]
pub enum Block {
    Air = 0,
    Grass,
    Dirt,
    Stone,
    Sand,
    Sandstone,
    Snow,
    Gravel,
    Water,
    OakLog,
    OakLeaves,
    SpruceLog,
    SpruceLeaves,
    Cactus,
    Planks,
    Bricks,
    StoneBricks,
    RoofTiles,
    Terracotta,
    RedWool,
    YellowWool,
    BlueWool,
    WhiteWool,
    BlackWool,
    Glowstone,
}

/// Every block, in `repr` order (so `ALL[b as usize] == b`).
pub const ALL: [Block; 25] = [
    Block::Air,
    Block::Grass,
    Block::Dirt,
    Block::Stone,
    Block::Sand,
    Block::Sandstone,
    Block::Snow,
    Block::Gravel,
    Block::Water,
    Block::OakLog,
    Block::OakLeaves,
    Block::SpruceLog,
    Block::SpruceLeaves,
    Block::Cactus,
    Block::Planks,
    Block::Bricks,
    Block::StoneBricks,
    Block::RoofTiles,
    Block::Terracotta,
    Block::RedWool,
    Block::YellowWool,
    Block::BlueWool,
    Block::WhiteWool,
    Block::BlackWool,
    Block::Glowstone,
];

/// The colour bands that make pillars recognisable landmarks.
pub const WOOLS: [Block; 6] =
    [Block::RedWool, Block::YellowWool, Block::BlueWool, Block::WhiteWool, Block::BlackWool, Block::Glowstone];

/// Which face of a block a ray hit, by outward normal.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Face {
    Top,
    Bottom,
    /// Normal ±x.
    SideX,
    /// Normal ±z.
    SideZ,
}

/// How a face's 8×8 texels vary around the base colour.
enum Pattern {
    Speckle(f64),
    /// Vertical grain (logs, cactus).
    Grain,
    /// Horizontal boards.
    Boards,
    /// Running-bond bricks with mortar lines.
    Bricks,
    /// Grass block side: green top rows over dirt.
    GrassSide,
    /// Flat, with gentle ripples.
    Ripples,
}

impl Block {
    pub fn from_u8(v: u8) -> Block {
        ALL.get(v as usize).copied().unwrap_or(Block::Stone)
    }

    pub fn is_solid(self) -> bool {
        self != Block::Air
    }

    /// Whether a player may end a path standing on this block.
    pub fn is_standable(self) -> bool {
        !matches!(self, Block::Air | Block::Water | Block::OakLeaves | Block::SpruceLeaves | Block::Cactus)
    }

    fn base_rgb(self, face: Face) -> [f64; 3] {
        let c = match self {
            Block::Air => [0, 0, 0],
            Block::Grass if face == Face::Top => [96, 160, 60],
            Block::Grass | Block::Dirt => [134, 96, 67],
            Block::Stone => [125, 125, 125],
            Block::Sand => [219, 207, 163],
            Block::Sandstone => [216, 200, 150],
            Block::Snow => [240, 245, 250],
            Block::Gravel => [136, 126, 126],
            Block::Water => [50, 90, 200],
            Block::OakLog if face == Face::Top || face == Face::Bottom => [176, 143, 92],
            Block::OakLog => [102, 81, 50],
            Block::OakLeaves => [58, 120, 40],
            Block::SpruceLog if face == Face::Top || face == Face::Bottom => [120, 90, 60],
            Block::SpruceLog => [60, 42, 26],
            Block::SpruceLeaves => [50, 80, 55],
            Block::Cactus => [80, 130, 50],
            Block::Planks => [162, 130, 78],
            Block::Bricks => [150, 74, 60],
            Block::StoneBricks => [110, 110, 115],
            Block::RoofTiles => [70, 60, 110],
            Block::Terracotta => [160, 84, 50],
            Block::RedWool => [200, 40, 40],
            Block::YellowWool => [240, 200, 40],
            Block::BlueWool => [50, 70, 190],
            Block::WhiteWool => [235, 235, 235],
            Block::BlackWool => [30, 30, 35],
            Block::Glowstone => [250, 220, 130],
        };
        [c[0] as f64, c[1] as f64, c[2] as f64]
    }

    fn pattern(self, face: Face) -> Pattern {
        let side = matches!(face, Face::SideX | Face::SideZ);
        match self {
            Block::Grass if side => Pattern::GrassSide,
            Block::OakLog | Block::SpruceLog | Block::Cactus if side => Pattern::Grain,
            Block::Planks => Pattern::Boards,
            Block::Bricks | Block::StoneBricks => Pattern::Bricks,
            Block::Water => Pattern::Ripples,
            Block::OakLeaves | Block::SpruceLeaves => Pattern::Speckle(0.45),
            Block::Snow | Block::Sand | Block::Sandstone => Pattern::Speckle(0.08),
            Block::RedWool | Block::YellowWool | Block::BlueWool | Block::WhiteWool | Block::BlackWool => {
                Pattern::Speckle(0.06)
            }
            _ => Pattern::Speckle(0.2),
        }
    }

    /// The unlit colour of texel `(tu, tv)` (each in 0..8, `tv` counting
    /// down from the top of a side face) of `face` on the block at `cell`.
    pub fn texel(self, face: Face, cell: [i32; 3], tu: u32, tv: u32) -> [f64; 3] {
        let base = self.base_rgb(face);
        let noise = |salt: i64| unit(self as u64, &[cell[0] as i64, cell[1] as i64, cell[2] as i64, tu as i64, tv as i64, salt]) - 0.5;
        let factor = match self.pattern(face) {
            Pattern::Speckle(amp) => 1.0 + amp * noise(0),
            Pattern::Grain => 1.0 + 0.25 * (if tu.is_multiple_of(3) { -0.5 } else { 0.1 }) + 0.1 * noise(0),
            Pattern::Boards => 1.0 + if tv % 4 == 3 { -0.3 } else { 0.08 * noise(0) },
            Pattern::Bricks => {
                let offset = if (tv / 2).is_multiple_of(2) { 0 } else { 2 };
                if tv % 2 == 1 || (tu + offset).is_multiple_of(4) { 1.35 } else { 1.0 + 0.12 * noise(0) }
            }
            Pattern::GrassSide if tv < 2 => {
                return scale(Block::Grass.base_rgb(Face::Top), 1.0 + 0.15 * noise(0));
            }
            Pattern::GrassSide => 1.0 + 0.2 * noise(0),
            Pattern::Ripples => 1.0 + 0.1 * ((tu + 2 * tv) as f64 * 0.9).sin(),
        };
        scale(base, factor)
    }
}

fn scale(c: [f64; 3], f: f64) -> [f64; 3] {
    [c[0] * f, c[1] * f, c[2] * f]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn all_matches_repr_order() {
        for (i, b) in ALL.iter().enumerate() {
            assert_eq!(*b as usize, i);
            assert_eq!(Block::from_u8(i as u8), *b);
        }
    }
}
