//! The voxel world: seeded terrain with biomes, trees and landmark
//! structures. World axes are Minecraft's (x east, y up, z south); block
//! `(x, y, z)` fills the unit cube `[x, x+1) × [y, y+1) × [z, z+1)`.

use crate::blocks::{Block, WOOLS};
use crate::noise::{Rng, fbm2, hash, smoothstep, unit_of, value2};

/// Blocks along x and z of a default world: room for ABCA legs of ±50 blocks
/// each from the centre plus the view distance.
pub const DEFAULT_SIZE: i32 = 384;
/// Blocks along y.
pub const HEIGHT: i32 = 64;
/// Water fills air below this level.
pub const SEA_LEVEL: i32 = 17;

#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Biome {
    Plains,
    Forest,
    Desert,
    Snowy,
    Mountains,
    Badlands,
}

pub struct World {
    seed: u64,
    size: i32,
    blocks: Vec<u8>,
    biomes: Vec<Biome>,
}

impl World {
    /// Builds the world for `seed`; the same seed gives the same blocks.
    pub fn generate(seed: u64) -> World {
        Self::generate_sized(seed, DEFAULT_SIZE)
    }

    /// A flat world: stone up to `ground`, grass at `ground`, air above. For
    /// tests that need exact geometry.
    pub fn flat(size: i32, ground: i32) -> World {
        let size = size.max(16);
        let n = (size * size) as usize;
        let mut world = World { seed: 0, size, blocks: vec![0; n * HEIGHT as usize], biomes: vec![Biome::Plains; n] };
        for z in 0..size {
            for x in 0..size {
                for y in 0..=ground {
                    world.set(x, y, z, if y == ground { Block::Grass } else { Block::Stone });
                }
            }
        }
        world
    }

    pub fn generate_sized(seed: u64, size: i32) -> World {
        let size = size.max(16);
        let n = (size * size) as usize;
        let mut world = World { seed, size, blocks: vec![0; n * HEIGHT as usize], biomes: vec![Biome::Plains; n] };
        world.fill_terrain();
        world.plant_vegetation();
        world.build_landmarks();
        world
    }

    pub fn seed(&self) -> u64 {
        self.seed
    }

    /// Blocks along x and along z.
    pub fn size(&self) -> i32 {
        self.size
    }

    pub fn in_bounds(&self, x: i32, y: i32, z: i32) -> bool {
        x >= 0 && z >= 0 && y >= 0 && x < self.size && z < self.size && y < HEIGHT
    }

    /// The block at a cell; outside the world everything is air.
    #[inline]
    pub fn get(&self, x: i32, y: i32, z: i32) -> Block {
        if self.in_bounds(x, y, z) { Block::from_u8(self.blocks[self.index(x, y, z)]) } else { Block::Air }
    }

    /// Raw block code for the renderer's inner loop (0 = air, also outside).
    #[inline]
    pub(crate) fn code(&self, x: i32, y: i32, z: i32) -> u8 {
        if self.in_bounds(x, y, z) { self.blocks[self.index(x, y, z)] } else { 0 }
    }

    pub fn biome(&self, x: i32, z: i32) -> Biome {
        let (x, z) = (x.clamp(0, self.size - 1), z.clamp(0, self.size - 1));
        self.biomes[(z * self.size + x) as usize]
    }

    /// The highest non-air cell of a column, if any.
    pub fn top(&self, x: i32, z: i32) -> Option<i32> {
        (0..HEIGHT).rev().find(|&y| self.get(x, y, z).is_solid())
    }

    /// Places a block (ignored outside the world): for building test scenes.
    pub fn set(&mut self, x: i32, y: i32, z: i32, b: Block) {
        if self.in_bounds(x, y, z) {
            let i = self.index(x, y, z);
            self.blocks[i] = b as u8;
        }
    }

    /// y-major columns keep a column's cells together for the path finder.
    #[inline]
    fn index(&self, x: i32, y: i32, z: i32) -> usize {
        ((z * self.size + x) * HEIGHT + y) as usize
    }

    /// Continuous fields first (height, temperature, moisture, ruggedness),
    /// so biome borders do not make cliffs; the biome only picks materials.
    fn fill_terrain(&mut self) {
        let s = self.seed;
        for z in 0..self.size {
            for x in 0..self.size {
                let (fx, fz) = (x as f64, z as f64);
                let temperature = fbm2(s ^ 0x7e3, fx, fz, 110.0, 2);
                let moisture = fbm2(s ^ 0x5a1, fx, fz, 90.0, 2);
                let rugged = fbm2(s ^ 0x3c9, fx, fz, 80.0, 2);
                let biome = if rugged > 0.66 {
                    Biome::Mountains
                } else if temperature < 0.4 {
                    Biome::Snowy
                } else if temperature > 0.58 {
                    if moisture < 0.5 { Biome::Desert } else { Biome::Badlands }
                } else if moisture > 0.52 {
                    Biome::Forest
                } else {
                    Biome::Plains
                };
                let hills = 16.0 * fbm2(s ^ 0x11, fx, fz, 40.0, 4);
                let peaks = 26.0 * smoothstep(0.55, 0.75, rugged) * fbm2(s ^ 0x22, fx, fz, 18.0, 3);
                let flatten = if biome == Biome::Desert { 0.6 } else { 1.0 };
                let h = (14.0 + flatten * hills + peaks).round() as i32;
                let h = h.clamp(4, HEIGHT - 16);
                self.biomes[(z * self.size + x) as usize] = biome;
                self.fill_column(x, z, h, biome);
            }
        }
    }

    fn fill_column(&mut self, x: i32, z: i32, h: i32, biome: Biome) {
        for y in 0..=h {
            let depth = h - y;
            let b = match biome {
                _ if depth > 3 => Block::Stone,
                Biome::Plains | Biome::Forest => {
                    if depth == 0 && h >= SEA_LEVEL { Block::Grass } else if h < SEA_LEVEL { Block::Sand } else { Block::Dirt }
                }
                Biome::Desert => if depth < 3 { Block::Sand } else { Block::Sandstone },
                Biome::Snowy => if depth == 0 { Block::Snow } else { Block::Dirt },
                Biome::Mountains => {
                    if depth == 0 && h > 36 {
                        Block::Snow
                    } else if value2(self.seed ^ 0x9f, x as f64, z as f64, 5.0) > 0.7 {
                        Block::Gravel
                    } else {
                        Block::Stone
                    }
                }
                // Layered clay: bands by height, as in Minecraft's badlands.
                Biome::Badlands => match y.rem_euclid(5) {
                    0 => Block::Sandstone,
                    2 => Block::Bricks,
                    _ => Block::Terracotta,
                },
            };
            self.set(x, y, z, b);
        }
        for y in h + 1..SEA_LEVEL {
            self.set(x, y, z, Block::Water);
        }
    }

    fn plant_vegetation(&mut self) {
        for z in 2..self.size - 2 {
            for x in 2..self.size - 2 {
                let Some(y) = self.top(x, z) else { continue };
                let ground = self.get(x, y, z);
                let density = match (self.biome(x, z), ground) {
                    (Biome::Forest, Block::Grass) => 0.035,
                    (Biome::Plains, Block::Grass) => 0.004,
                    (Biome::Snowy, Block::Snow) => 0.012,
                    (Biome::Desert, Block::Sand) => 0.004,
                    (Biome::Mountains, Block::Stone) => 0.002,
                    _ => 0.0,
                };
                let roll = hash(self.seed ^ 0x7ee, &[x as i64, z as i64]);
                if unit_of(roll) >= density {
                    continue;
                }
                let mut rng = Rng::new(roll);
                match self.biome(x, z) {
                    Biome::Desert => self.cactus(x, y + 1, z, &mut rng),
                    Biome::Snowy | Biome::Mountains => self.spruce(x, y + 1, z, &mut rng),
                    _ => self.oak(x, y + 1, z, &mut rng),
                }
            }
        }
    }

    fn oak(&mut self, x: i32, y: i32, z: i32, rng: &mut Rng) {
        let trunk = rng.range(4, 7) as i32;
        for dy in -2..=1 {
            let r: i32 = if dy == 1 { 1 } else { 2 };
            for dz in -r..=r {
                for dx in -r..=r {
                    let corner = dx.abs() == r && dz.abs() == r;
                    if corner && rng.chance(0.6) {
                        continue;
                    }
                    if !self.get(x + dx, y + trunk + dy, z + dz).is_solid() {
                        self.set(x + dx, y + trunk + dy, z + dz, Block::OakLeaves);
                    }
                }
            }
        }
        for dy in 0..trunk {
            self.set(x, y + dy, z, Block::OakLog);
        }
    }

    fn spruce(&mut self, x: i32, y: i32, z: i32, rng: &mut Rng) {
        let trunk = rng.range(6, 9) as i32;
        for dy in 2..=trunk {
            let r = ((trunk - dy) / 2).min(2) + i32::from(dy % 2 == 0 && dy < trunk - 1);
            for dz in -r..=r {
                for dx in -r..=r {
                    if dx.abs() + dz.abs() <= r + 1 && !self.get(x + dx, y + dy, z + dz).is_solid() {
                        self.set(x + dx, y + dy, z + dz, Block::SpruceLeaves);
                    }
                }
            }
        }
        self.set(x, y + trunk + 1, z, Block::SpruceLeaves);
        for dy in 0..trunk {
            self.set(x, y + dy, z, Block::SpruceLog);
        }
    }

    fn cactus(&mut self, x: i32, y: i32, z: i32, rng: &mut Rng) {
        for dy in 0..rng.range(2, 5) as i32 {
            self.set(x, y + dy, z, Block::Cactus);
        }
    }

    /// One chance of a landmark per 20×20 cell of a jittered grid: coloured
    /// pillars (recognisable from afar), houses (walls, a door, an
    /// overhanging roof), free-standing walls (occluders) and arches.
    fn build_landmarks(&mut self) {
        const CELL: i32 = 20;
        for cz in 0..self.size / CELL {
            for cx in 0..self.size / CELL {
                let mut rng = Rng::new(hash(self.seed ^ 0x1a2d, &[cx as i64, cz as i64]));
                if !rng.chance(0.6) {
                    continue;
                }
                let x = cx * CELL + rng.range(5, (CELL - 5) as i64) as i32;
                let z = cz * CELL + rng.range(5, (CELL - 5) as i64) as i32;
                let Some(ground) = self.top(x, z) else { continue };
                if self.get(x, ground, z) == Block::Water {
                    continue;
                }
                match rng.range(0, 20) {
                    0..=6 => self.pillar(x, ground + 1, z, &mut rng),
                    7..=13 => self.house(x, ground + 1, z, &mut rng),
                    14..=17 => self.wall(x, z, &mut rng),
                    _ => self.arch(x, ground + 1, z, &mut rng),
                }
            }
        }
    }

    fn pillar(&mut self, x: i32, y: i32, z: i32, rng: &mut Rng) {
        let height = rng.range(7, 15) as i32;
        let mut band = WOOLS[rng.range(0, 5) as usize];
        for dy in -3..height {
            if dy >= 0 && dy % 3 == 0 {
                band = WOOLS[rng.range(0, 5) as usize];
            }
            for (dx, dz) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
                // Foundations reach down through slopes to the ground.
                if dy >= 0 || !self.get(x + dx, y + dy, z + dz).is_solid() {
                    self.set(x + dx, y + dy, z + dz, band);
                }
            }
        }
        for (dx, dz) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
            self.set(x + dx, y + height, z + dz, Block::Glowstone);
        }
    }

    fn house(&mut self, x0: i32, floor: i32, z0: i32, rng: &mut Rng) {
        let (w, d) = (rng.range(5, 9) as i32, rng.range(5, 9) as i32);
        let wall = [Block::Planks, Block::Bricks, Block::StoneBricks, Block::Sandstone][rng.range(0, 4) as usize];
        let door_side = rng.range(0, 4);
        let walls = 4;
        for dz in -1..=d {
            for dx in -1..=w {
                let (x, z) = (x0 + dx, z0 + dz);
                let edge = dx == 0 || dz == 0 || dx == w - 1 || dz == d - 1;
                let inside = (0..w).contains(&dx) && (0..d).contains(&dz);
                // Clear the volume, lay a floor and fill foundations.
                for y in floor..floor + walls + 2 {
                    self.set(x, y, z, Block::Air);
                }
                if inside {
                    for y in (floor - 4..floor).rev() {
                        self.set(x, y, z, if y == floor - 1 { Block::Planks } else { Block::Stone });
                    }
                }
                // The roof overhangs the walls by one block on every side.
                self.set(x, floor + walls, z, Block::RoofTiles);
                if inside && edge {
                    let door = match door_side {
                        0 => dz == 0 && dx == w / 2,
                        1 => dz == d - 1 && dx == w / 2,
                        2 => dx == 0 && dz == d / 2,
                        _ => dx == w - 1 && dz == d / 2,
                    };
                    for y in floor..floor + walls {
                        let window = y == floor + 2 && (dx + dz) % 3 == 1 && !door;
                        if !(window || door && y < floor + 2) {
                            self.set(x, y, z, wall);
                        }
                    }
                }
            }
        }
    }

    fn wall(&mut self, x0: i32, z0: i32, rng: &mut Rng) {
        let length = rng.range(8, 17) as i32;
        let along_x = rng.chance(0.5);
        let height = rng.range(3, 5) as i32;
        for i in 0..length {
            let (x, z) = if along_x { (x0 + i, z0) } else { (x0, z0 + i) };
            let Some(ground) = self.top(x, z) else { continue };
            for y in ground + 1..=ground + height {
                self.set(x, y, z, Block::StoneBricks);
            }
        }
    }

    fn arch(&mut self, x0: i32, y: i32, z0: i32, rng: &mut Rng) {
        let span = rng.range(4, 7) as i32;
        let along_x = rng.chance(0.5);
        let at = |i: i32| if along_x { (x0 + i, z0) } else { (x0, z0 + i) };
        for i in 0..=span {
            let (x, z) = at(i);
            self.set(x, y + 4, z, Block::Bricks);
            if i == 0 || i == span {
                for dy in -3..4 {
                    if dy >= 0 || !self.get(x, y + dy, z).is_solid() {
                        self.set(x, y + dy, z, Block::Bricks);
                    }
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn same_seed_same_blocks_other_seed_other_blocks() {
        let a = World::generate_sized(5, 96);
        let b = World::generate_sized(5, 96);
        let c = World::generate_sized(6, 96);
        assert!(a.blocks == b.blocks);
        let differ = a.blocks.iter().zip(&c.blocks).filter(|(p, q)| p != q).count();
        assert!(differ > a.blocks.len() / 100, "seeds 5 and 6 differ in only {differ} cells");
    }

    #[test]
    fn worlds_hold_several_biomes_and_landmarks() {
        let mut biomes = std::collections::HashSet::new();
        let mut pillars = 0;
        for seed in 0..4 {
            let w = World::generate(seed);
            for z in (0..w.size()).step_by(8) {
                for x in (0..w.size()).step_by(8) {
                    biomes.insert(w.biome(x, z) as u8);
                }
            }
            pillars += w.blocks.iter().filter(|&&b| b == Block::Glowstone as u8).count() / 4;
        }
        assert!(biomes.len() >= 4, "only {} biomes in four worlds", biomes.len());
        assert!(pillars >= 8, "only {pillars} pillars in four worlds");
    }
}
