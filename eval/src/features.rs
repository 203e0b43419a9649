//! Learned perceptual metrics from ONNX feature networks the user supplies
//! (their real weights cannot be downloaded here; docs/metrics.md says how
//! to export them). The networks give features; the arithmetic is here.
//!
//! Contracts, by tensor name (float32, images RGB in [-1, 1], NCHW):
//! - LPIPS: input `image` (B,3,H,W); outputs `feat0..featL-1` (B,C_l,H_l,W_l)
//!   and `weight0..weightL-1` (C_l), the learned non-negative channel weights.
//!   d = Σ_l mean_hw Σ_c w_lc (f̂0 − f̂1)², f̂ = f / (‖f‖_c + 1e-10).
//! - DreamSim-style embedding: input `image`, output `embedding` (B,D);
//!   d = 1 − cos(e0, e1).
//! - FVD: input `video` (B,3,T,H,W), output `features` (B,D); the Fréchet
//!   distance between Gaussians fitted to real and generated clip features.

use std::path::Path;

use model::{Graph, ModelError, RuntimeOptions, Tensor};

#[derive(Debug, thiserror::Error)]
pub enum FeatureError {
    #[error(transparent)]
    Model(#[from] ModelError),
    #[error("{path}: {message}")]
    Contract { path: String, message: String },
}

fn contract(path: &Path, message: impl Into<String>) -> FeatureError {
    FeatureError::Contract { path: path.display().to_string(), message: message.into() }
}

/// Interleaved RGB u8 images of one size to (B,3,H,W) in [-1, 1].
pub fn images_to_tensor(images: &[&[u8]], width: usize, height: usize) -> Tensor {
    let plane = width * height;
    let mut data = Vec::with_capacity(images.len() * 3 * plane);
    for img in images {
        assert_eq!(img.len(), 3 * plane, "images_to_tensor: image size");
        for c in 0..3 {
            data.extend((0..plane).map(|p| img[3 * p + c] as f32 / 127.5 - 1.0));
        }
    }
    Tensor::new(vec![images.len(), 3, height, width], data)
}

fn open(path: &Path, options: RuntimeOptions, input: &str) -> Result<Graph, FeatureError> {
    let g = Graph::open_self_described(path, options)?;
    let inputs: Vec<&str> = g.spec().inputs.iter().map(|t| t.name.as_str()).collect();
    if inputs != [input] {
        return Err(contract(path, format!("expected one input called {input:?}, found {inputs:?}")));
    }
    Ok(g)
}

fn output_index(g: &Graph, path: &Path, name: &str) -> Result<usize, FeatureError> {
    g.spec().outputs.iter().position(|o| o.name == name).ok_or_else(|| {
        let names: Vec<&str> = g.spec().outputs.iter().map(|o| o.name.as_str()).collect();
        contract(path, format!("no output called {name:?} (outputs: {names:?})"))
    })
}

pub struct Lpips {
    graph: Graph,
    /// (feature output, weight output) per layer.
    layers: Vec<(usize, usize)>,
}

impl Lpips {
    pub fn open(path: &Path, options: RuntimeOptions) -> Result<Lpips, FeatureError> {
        let graph = open(path, options, "image")?;
        let mut layers = Vec::new();
        while let Some(f) = graph.spec().outputs.iter().position(|o| o.name == format!("feat{}", layers.len())) {
            layers.push((f, output_index(&graph, path, &format!("weight{}", layers.len()))?));
        }
        if layers.is_empty() {
            return Err(contract(path, "an LPIPS network needs outputs feat0, weight0, feat1, weight1, ..."));
        }
        Ok(Lpips { graph, layers })
    }

    /// The LPIPS distance of each pair `(a[i], b[i])`.
    pub fn distances(&self, a: &[&[u8]], b: &[&[u8]], width: usize, height: usize) -> Result<Vec<f64>, FeatureError> {
        assert_eq!(a.len(), b.len(), "lpips: unpaired images");
        let both: Vec<&[u8]> = a.iter().chain(b).copied().collect();
        let out = self.graph.run(&[("image", &images_to_tensor(&both, width, height))])?;
        let n = a.len();
        let mut d = vec![0.0; n];
        for &(fi, wi) in &self.layers {
            let (f, w) = (&out[fi], &out[wi]);
            let [_, c, h, wd] = f.shape[..] else { return Err(contract(Path::new("lpips"), format!("feature shape {:?} is not 4-D", f.shape))) };
            if w.data.len() != c {
                return Err(contract(Path::new("lpips"), format!("{} channel weights for {c} channels", w.data.len())));
            }
            let plane = h * wd;
            for (i, di) in d.iter_mut().enumerate() {
                let (x, y) = (&f.data[i * c * plane..(i + 1) * c * plane], &f.data[(n + i) * c * plane..(n + i + 1) * c * plane]);
                let mut layer = 0.0;
                for p in 0..plane {
                    let nx = (0..c).map(|k| (x[k * plane + p] as f64).powi(2)).sum::<f64>().sqrt() + 1e-10;
                    let ny = (0..c).map(|k| (y[k * plane + p] as f64).powi(2)).sum::<f64>().sqrt() + 1e-10;
                    layer += (0..c).map(|k| w.data[k] as f64 * (x[k * plane + p] as f64 / nx - y[k * plane + p] as f64 / ny).powi(2)).sum::<f64>();
                }
                *di += layer / plane as f64;
            }
        }
        Ok(d)
    }
}

pub struct Embedding {
    graph: Graph,
}

impl Embedding {
    pub fn open(path: &Path, options: RuntimeOptions) -> Result<Embedding, FeatureError> {
        let graph = open(path, options, "image")?;
        output_index(&graph, path, "embedding")?;
        Ok(Embedding { graph })
    }

    /// `1 − cos` between the embeddings of each pair.
    pub fn distances(&self, a: &[&[u8]], b: &[&[u8]], width: usize, height: usize) -> Result<Vec<f64>, FeatureError> {
        let both: Vec<&[u8]> = a.iter().chain(b).copied().collect();
        let e = self.graph.run(&[("image", &images_to_tensor(&both, width, height))])?.remove(0);
        let dim = e.data.len() / both.len().max(1);
        let row = |i: usize| &e.data[i * dim..(i + 1) * dim];
        Ok((0..a.len())
            .map(|i| {
                let (x, y) = (row(i), row(a.len() + i));
                let dot: f64 = x.iter().zip(y).map(|(&p, &q)| p as f64 * q as f64).sum();
                let norm = |v: &[f32]| v.iter().map(|&p| (p as f64).powi(2)).sum::<f64>().sqrt();
                1.0 - dot / (norm(x) * norm(y)).max(1e-12)
            })
            .collect())
    }
}

pub struct VideoFeatures {
    graph: Graph,
}

impl VideoFeatures {
    pub fn open(path: &Path, options: RuntimeOptions) -> Result<VideoFeatures, FeatureError> {
        let graph = open(path, options, "video")?;
        output_index(&graph, path, "features")?;
        match graph.spec().inputs[0].dims().get(2) {
            Some(&t) if t > 0 => Ok(VideoFeatures { graph }),
            _ => Err(contract(path, "input `video` must be (batch, 3, T, H, W) with a fixed clip length T")),
        }
    }

    /// Frames per clip the network takes.
    pub fn clip_len(&self) -> usize {
        self.graph.spec().inputs[0].dims()[2] as usize
    }

    /// Features of clips, each `clip_len` interleaved RGB frames.
    pub fn features(&self, clips: &[Vec<&[u8]>], width: usize, height: usize) -> Result<Vec<Vec<f64>>, FeatureError> {
        let t = self.clip_len();
        let plane = width * height;
        let mut data = Vec::with_capacity(clips.len() * 3 * t * plane);
        for clip in clips {
            if clip.len() != t {
                return Err(contract(Path::new("fvd"), format!("a clip of {} frames; the network takes {t}", clip.len())));
            }
            for c in 0..3 {
                for frame in clip {
                    data.extend((0..plane).map(|p| frame[3 * p + c] as f32 / 127.5 - 1.0));
                }
            }
        }
        let out = self.graph.run(&[("video", &Tensor::new(vec![clips.len(), 3, t, height, width], data))])?.remove(0);
        let dim = out.data.len() / clips.len().max(1);
        Ok(out.data.chunks_exact(dim.max(1)).map(|r| r.iter().map(|&v| v as f64).collect()).collect())
    }
}

fn mean_cov(x: &[Vec<f64>]) -> (Vec<f64>, Vec<f64>) {
    let (n, d) = (x.len(), x[0].len());
    let mean: Vec<f64> = (0..d).map(|j| x.iter().map(|r| r[j]).sum::<f64>() / n as f64).collect();
    let mut cov = vec![0.0; d * d];
    for r in x {
        for i in 0..d {
            for j in 0..d {
                cov[i * d + j] += (r[i] - mean[i]) * (r[j] - mean[j]);
            }
        }
    }
    let denom = (n.max(2) - 1) as f64;
    cov.iter_mut().for_each(|v| *v /= denom);
    (mean, cov)
}

/// Eigenvalues and eigenvectors (columns) of a symmetric matrix, by cyclic Jacobi rotations.
fn symmetric_eigen(mut a: Vec<f64>, n: usize) -> (Vec<f64>, Vec<f64>) {
    let mut v = vec![0.0; n * n];
    (0..n).for_each(|i| v[i * n + i] = 1.0);
    for _sweep in 0..100 {
        let off: f64 = (0..n).flat_map(|i| (0..n).filter(move |&j| j != i).map(move |j| (i, j))).map(|(i, j)| a[i * n + j].powi(2)).sum();
        let scale: f64 = a.iter().map(|x| x * x).sum::<f64>().max(f64::MIN_POSITIVE);
        if off <= 1e-30 * scale {
            break;
        }
        for p in 0..n {
            for q in p + 1..n {
                let apq = a[p * n + q];
                if apq.abs() < 1e-300 {
                    continue;
                }
                let theta = (a[q * n + q] - a[p * n + p]) / (2.0 * apq);
                let t = theta.signum() / (theta.abs() + (theta * theta + 1.0).sqrt());
                let t = if theta == 0.0 { 1.0 } else { t };
                let (c, s) = (1.0 / (t * t + 1.0).sqrt(), t / (t * t + 1.0).sqrt());
                for k in 0..n {
                    let (akp, akq) = (a[k * n + p], a[k * n + q]);
                    a[k * n + p] = c * akp - s * akq;
                    a[k * n + q] = s * akp + c * akq;
                }
                for k in 0..n {
                    let (apk, aqk) = (a[p * n + k], a[q * n + k]);
                    a[p * n + k] = c * apk - s * aqk;
                    a[q * n + k] = s * apk + c * aqk;
                }
                for k in 0..n {
                    let (vkp, vkq) = (v[k * n + p], v[k * n + q]);
                    v[k * n + p] = c * vkp - s * vkq;
                    v[k * n + q] = s * vkp + c * vkq;
                }
            }
        }
    }
    ((0..n).map(|i| a[i * n + i]).collect(), v)
}

fn matmul(a: &[f64], b: &[f64], n: usize) -> Vec<f64> {
    let mut c = vec![0.0; n * n];
    for i in 0..n {
        for k in 0..n {
            let aik = a[i * n + k];
            for j in 0..n {
                c[i * n + j] += aik * b[k * n + j];
            }
        }
    }
    c
}

/// `‖μ_a − μ_b‖² + Tr(Σ_a + Σ_b − 2 (Σ_a Σ_b)^½)`, with the trace of the
/// square root taken as Σ √λ of the symmetric `Σ_a^½ Σ_b Σ_a^½`.
pub fn frechet_distance(a: &[Vec<f64>], b: &[Vec<f64>]) -> f64 {
    assert!(!a.is_empty() && !b.is_empty() && a[0].len() == b[0].len(), "frechet_distance: empty or mismatched features");
    let d = a[0].len();
    let (ma, sa) = mean_cov(a);
    let (mb, sb) = mean_cov(b);
    let (la, va) = symmetric_eigen(sa.clone(), d);
    // Σ_a^½ = V diag(√λ) Vᵀ
    let mut root = vec![0.0; d * d];
    for i in 0..d {
        for j in 0..d {
            root[i * d + j] = (0..d).map(|k| va[i * d + k] * la[k].max(0.0).sqrt() * va[j * d + k]).sum();
        }
    }
    let m = matmul(&matmul(&root, &sb, d), &root, d);
    let sym: Vec<f64> = (0..d * d).map(|i| 0.5 * (m[i] + m[(i % d) * d + i / d])).collect();
    let trace_sqrt: f64 = symmetric_eigen(sym, d).0.iter().map(|l| l.max(0.0).sqrt()).sum();
    let trace = |s: &[f64]| (0..d).map(|i| s[i * d + i]).sum::<f64>();
    ma.iter().zip(&mb).map(|(x, y)| (x - y).powi(2)).sum::<f64>() + trace(&sa) + trace(&sb) - 2.0 * trace_sqrt
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn jacobi_recovers_a_known_spectrum() {
        // Q diag(5, 2, 0.5) Qᵀ for a rotation Q.
        let (c, s) = (0.6f64, 0.8f64);
        let q = [c, -s, 0.0, s, c, 0.0, 0.0, 0.0, 1.0];
        let d = [5.0, 0.0, 0.0, 0.0, 2.0, 0.0, 0.0, 0.0, 0.5];
        let qt: Vec<f64> = (0..9).map(|i| q[(i % 3) * 3 + i / 3]).collect();
        let a = matmul(&matmul(&q, &d, 3), &qt, 3);
        let mut l = symmetric_eigen(a, 3).0;
        l.sort_by(f64::total_cmp);
        for (got, want) in l.iter().zip([0.5, 2.0, 5.0]) {
            assert!((got - want).abs() < 1e-12, "{l:?}");
        }
    }

    #[test]
    fn frechet_distance_of_shifted_and_scaled_gaussians() {
        // Same covariance, means 3 apart in one coordinate: distance 9.
        let a: Vec<Vec<f64>> = (0..50).map(|i| vec![(i as f64 * 0.37).sin(), (i as f64 * 1.3).cos()]).collect();
        let b: Vec<Vec<f64>> = a.iter().map(|r| vec![r[0] + 3.0, r[1]]).collect();
        assert!((frechet_distance(&a, &b) - 9.0).abs() < 1e-9);
        assert!(frechet_distance(&a, &a).abs() < 1e-9);
        // Scaling by 2 about the mean: Tr(Σ + 4Σ − 2·2Σ) = Tr(Σ).
        let (m, s) = mean_cov(&a);
        let c: Vec<Vec<f64>> = a.iter().map(|r| vec![m[0] + 2.0 * (r[0] - m[0]), m[1] + 2.0 * (r[1] - m[1])]).collect();
        assert!((frechet_distance(&a, &c) - (s[0] + s[3])).abs() < 1e-9);
    }
}
