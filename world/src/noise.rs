//! Seeded hashing and value noise: the only randomness the world uses, so a
//! seed fixes every block and every texel on every machine.


/// A 64-bit avalanche hash of several integers (SplitMix64's finaliser,
/// chained). Equal inputs give equal outputs everywhere.
pub fn hash(seed: u64, parts: &[i64]) -> u64 {
    let mut h = seed ^ 0x9E37_79B9_7F4A_7C15;
    for &p in parts {
        h = mix(h ^ (p as u64).wrapping_mul(0xBF58_476D_1CE4_E5B9));
    }
    h
}

fn mix(mut z: u64) -> u64 {
    z = z.wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// A hash of the parts mapped to [0, 1).
pub fn unit(seed: u64, parts: &[i64]) -> f64 {
    unit_of(hash(seed, parts))
}

/// The top 53 bits of `h` as a float in [0, 1).
pub fn unit_of(h: u64) -> f64 {
    (h >> 11) as f64 / (1u64 << 53) as f64
}

/// Smooth 2-D value noise in [0, 1) with lattice spacing `scale` blocks.
pub fn value2(seed: u64, x: f64, z: f64, scale: f64) -> f64 {
    let (fx, fz) = (x / scale, z / scale);
    let (x0, z0) = (fx.floor(), fz.floor());
    let (tx, tz) = (smooth(fx - x0), smooth(fz - z0));
    let (ix, iz) = (x0 as i64, z0 as i64);
    let corner = |dx: i64, dz: i64| unit(seed, &[ix + dx, iz + dz]);
    let top = lerp(corner(0, 0), corner(1, 0), tx);
    let bottom = lerp(corner(0, 1), corner(1, 1), tx);
    lerp(top, bottom, tz)
}

/// Fractal sum of `octaves` value-noise layers, each at half the scale and
/// half the weight of the last, normalised to [0, 1).
pub fn fbm2(seed: u64, x: f64, z: f64, scale: f64, octaves: u32) -> f64 {
    let (mut total, mut weight, mut norm, mut s) = (0.0, 1.0, 0.0, scale);
    for octave in 0..octaves {
        total += weight * value2(seed.wrapping_add(octave as u64 * 7919), x, z, s);
        norm += weight;
        weight *= 0.5;
        s *= 0.5;
    }
    total / norm
}

/// 0 below `lo`, 1 above `hi`, a smooth cubic between.
pub fn smoothstep(lo: f64, hi: f64, v: f64) -> f64 {
    smooth(((v - lo) / (hi - lo)).clamp(0.0, 1.0))
}

fn smooth(t: f64) -> f64 {
    t * t * (3.0 - 2.0 * t)
}

fn lerp(a: f64, b: f64, t: f64) -> f64 {
    a + (b - a) * t
}

/// A small deterministic generator for choices made while building the world
/// and its trajectories. (Its stream is this crate's own — `mix` of a
/// SplitMix64-style counter — and fixes every committed figure, so it is not
/// swapped for the memory crate's `SplitMix64`, whose stream differs.)
#[derive(Clone, Debug)]
pub struct Rng(u64);

impl Rng {
    pub fn new(seed: u64) -> Self {
        Rng(seed)
    }

    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        mix(self.0)
    }

    /// Uniform in [0, 1).
    pub fn unit(&mut self) -> f64 {
        unit_of(self.next_u64())
    }

    /// Uniform integer in [lo, hi).
    pub fn range(&mut self, lo: i64, hi: i64) -> i64 {
        debug_assert!(hi > lo);
        lo + (self.next_u64() % (hi - lo) as u64) as i64
    }

    pub fn chance(&mut self, p: f64) -> bool {
        self.unit() < p
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn value_noise_is_continuous_and_bounded() {
        for i in 0..2000 {
            let x = i as f64 * 0.37 - 300.0;
            let a = value2(7, x, 0.5 * x, 16.0);
            let b = value2(7, x + 1e-3, 0.5 * x, 16.0);
            assert!((0.0..1.0).contains(&a));
            assert!((a - b).abs() < 1e-3, "jump of {} at x = {x}", (a - b).abs());
        }
    }

    #[test]
    fn seeds_change_the_noise() {
        let same = (0..100).filter(|&i| value2(1, i as f64 * 3.1, 2.0, 8.0) == value2(2, i as f64 * 3.1, 2.0, 8.0));
        assert!(same.count() < 5);
    }
}
