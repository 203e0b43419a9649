//! `manifest.json`: the contract between an export and this runtime
//! (docs/model.md lists every field). Parsed, then checked for consistency
//! before any graph is opened.

use std::path::{Path, PathBuf};

use memory::Intrinsics;
use serde::Deserialize;

use crate::error::ModelError;
use crate::tensor::Tensor;

pub const FORMAT: &str = "worldpack-model/1";

/// Inputs named `context_noise_r<rate>` carry a noise level per context slot.
pub const CONTEXT_NOISE_PREFIX: &str = "context_noise_r";

#[derive(Clone, Debug, Deserialize)]
pub struct Manifest {
    pub format: String,
    pub name: String,
    pub image: ImageSpec,
    pub intrinsics: Intrinsics,
    pub autoencoder: AutoencoderSpec,
    pub denoiser: DenoiserSpec,
    pub action: ActionSpec,
    pub diffusion: DiffusionSpec,
    /// How the weights were trained (absent in hand-made manifests).
    #[serde(default)]
    pub training: Option<TrainingSpec>,
    /// A geometry model's fusion head (run by `Model::predict`): a small pixel-space
    /// graph that blends the decoded frame with the fused reference of the
    /// warp sources (inputs `predicted`, `reference`, `landed`; output
    /// `image`). Absent: the decoded frame is the prediction.
    #[serde(default)]
    pub fusion: Option<GraphSpec>,
    /// How the model is served as its card measured it (absent: the server's own defaults).
    #[serde(default)]
    pub serving: Option<ServingSpec>,
    /// The model's version, as the trainer writes it (absent in older folders).
    #[serde(default)]
    pub version: Option<String>,
    /// SHA-256 of the folder's manifest, graphs and weights (the first 16 hex digits), set
    /// by [`Manifest::load`]: which exact model answered, whatever the folder is called.
    #[serde(skip)]
    pub digest: String,
}

/// The manifest's `serving` block (written by `worldpack train`): the policy, sampler, steps
/// and selection the model's held-out eval used. `worldpack serve` takes each as its default.
#[derive(Clone, Debug, Default, Deserialize)]
pub struct ServingSpec {
    pub policy: Option<String>,
    pub method: Option<String>,
    pub steps: Option<u64>,
    pub covisible: Option<bool>,
    /// How frames larger than the model's are shown (`model::full_size`), chosen on the
    /// world's development suite at that size; absent: `FullSize::default()`.
    #[serde(default)]
    pub full_size: Option<FullSizeSpec>,
}

/// The serving block's `full_size`: `full_size::FullSize`'s two choices.
#[derive(Clone, Copy, Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FullSizeSpec {
    pub agree_luma: f64,
    pub frames: usize,
    /// The least share of a model pixel the warp must cover to be shown there (default 0.75).
    #[serde(default)]
    pub min_cover: Option<f64>,
}

#[derive(Clone, Debug, Deserialize)]
pub struct TrainingSpec {
    /// The plans the weights were trained on (`worldpack`, `worldpack_keep_last`, ...).
    pub policy: String,
    /// Which view those plans scored against; absent in models exported
    /// before plans recorded it (they all used the target pose).
    #[serde(default)]
    pub plans_query: Option<memory::Query>,
}

#[derive(Clone, Debug, Deserialize)]
pub struct ImageSpec {
    pub width: usize,
    pub height: usize,
    pub channels: usize,
}

/// One dimension: a fixed size, or a named dynamic axis such as `"batch"`.
#[derive(Clone, Debug, PartialEq, Deserialize)]
#[serde(untagged)]
pub enum Dim {
    Fixed(i64),
    Named(String),
}

#[derive(Clone, Debug, Deserialize)]
pub struct TensorSpec {
    pub name: String,
    pub shape: Vec<Dim>,
    pub dtype: String,
}

impl TensorSpec {
    /// The shape with the dynamic axes as -1, as ONNX Runtime reports it.
    pub fn dims(&self) -> Vec<i64> {
        self.shape.iter().map(|d| if let Dim::Fixed(n) = d { *n } else { -1 }).collect()
    }
}

/// The fusion head's inputs, in order: the decoded frame and the fused
/// reference, (B, 3, H, W) in [-1, 1], and where the warp landed, (B, 1, H, W) of 0 or 1.
pub const FUSION_INPUTS: [&str; 3] = ["predicted", "reference", "landed"];

#[derive(Clone, Debug, Deserialize)]
pub struct GraphSpec {
    pub file: String,
    pub inputs: Vec<TensorSpec>,
    pub outputs: Vec<TensorSpec>,
}

impl GraphSpec {
    /// `inputs` (named, any order) in this spec's order, each checked
    /// against its declared shape: every backend refuses the same bad input
    /// with the same error, before anything runs.
    pub fn ordered_inputs<'a>(&self, inputs: &[(&str, &'a Tensor)]) -> Result<Vec<&'a Tensor>, ModelError> {
        self.inputs
            .iter()
            .map(|spec| {
                let Some((_, t)) = inputs.iter().find(|(n, _)| *n == spec.name) else {
                    return Err(ModelError::input(&spec.name, format!("{}: input missing", self.file)));
                };
                let want = spec.dims();
                let fits = want.len() == t.shape.len() && want.iter().zip(&t.shape).all(|(&w, &g)| w < 0 || w as usize == g);
                if !fits || t.data.len() != t.shape.iter().product::<usize>() {
                    return Err(ModelError::input(&spec.name, format!("expected shape {:?}, got {:?}", spec.shape, t.shape)));
                }
                Ok(*t)
            })
            .collect()
    }
}

#[derive(Clone, Debug, Deserialize)]
pub struct LatentSpec {
    pub channels: usize,
    pub height: usize,
    pub width: usize,
}

impl LatentSpec {
    pub fn len(&self) -> usize {
        self.channels * self.height * self.width
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

#[derive(Clone, Debug, Deserialize)]
pub struct AutoencoderSpec {
    pub encoder: GraphSpec,
    pub decoder: GraphSpec,
    pub latent: LatentSpec,
    pub latent_scale: f64,
}

#[derive(Clone, Debug, Deserialize)]
pub struct SlotSpec {
    pub rate: u32,
    pub count: usize,
    pub tokens_per_frame: u64,
}

#[derive(Clone, Debug, Deserialize)]
pub struct LayoutSpec {
    pub name: String,
    pub file: String,
    pub slots: Vec<SlotSpec>,
    pub frames: usize,
    pub context_tokens: u64,
    pub inputs: Vec<TensorSpec>,
    pub outputs: Vec<TensorSpec>,
}

impl LayoutSpec {
    /// Whether the graph takes a noise level per context slot.
    pub fn takes_context_noise(&self) -> bool {
        self.inputs.iter().any(|i| i.name.starts_with(CONTEXT_NOISE_PREFIX))
    }

    pub fn graph(&self) -> GraphSpec {
        GraphSpec { file: self.file.clone(), inputs: self.inputs.clone(), outputs: self.outputs.clone() }
    }
}

#[derive(Clone, Debug, Deserialize)]
pub struct DenoiserSpec {
    pub patch: u32,
    /// Trainable parameters, as the export counted them.
    #[serde(default)]
    pub parameters: Option<u64>,
    pub rates: Vec<u32>,
    pub layouts: Vec<LayoutSpec>,
    /// Present when the denoiser takes a noise level per context frame
    /// (`context_noise_r<rate>` inputs): which level marks which frames.
    #[serde(default)]
    pub context_noise: Option<ContextNoiseSpec>,
    /// Present when the denoiser takes a stored frame depth-warped into the
    /// target view (the geometry model; `crate::warp`).
    #[serde(default)]
    pub warp: Option<WarpSpec>,
}

/// The geometry model's extra input: the warped frame's scaled latent and
/// the share of each latent cell the warp covers, `channels` = latent + 1.
#[derive(Clone, Debug, Deserialize, PartialEq)]
pub struct WarpSpec {
    pub input: String,
    pub channels: usize,
    /// How many best-overlap frames with depth the runtime warps behind one
    /// z-buffer into this input (1 unless the manifest says otherwise).
    #[serde(default = "one_frame")]
    pub frames: usize,
}

fn one_frame() -> usize {
    1
}

/// The context noise levels the runtime feeds: training corrupted context
/// latents by a known level, and at inference the level says how far a frame
/// is to be trusted: observed frames are clean, generated ones are not.
#[derive(Clone, Copy, Debug, Deserialize, PartialEq)]
pub struct ContextNoiseSpec {
    pub observed_level: f32,
    pub generated_level: f32,
}

#[derive(Clone, Debug, Deserialize)]
pub struct ActionSpec {
    pub dim: usize,
}

#[derive(Clone, Debug, Deserialize)]
pub struct DiffusionSpec {
    pub timesteps: usize,
    pub beta_start: f64,
    pub beta_end: f64,
    pub prediction: String,
    /// Set for a few-step student: it is sampled by DDIM on exactly this grid.
    #[serde(default)]
    pub distilled: Option<DistilledSpec>,
}

/// A distilled student's sampler (`python -m worldpack_train distill`).
#[derive(Clone, Debug, Deserialize)]
pub struct DistilledSpec {
    /// Original timestep indices, descending; the last step lands on the clean frame.
    pub timesteps: Vec<usize>,
}

/// SHA-256 over the model files of `dir` (manifest.json, *.onnx, *.weights), by name in order.
fn folder_digest(dir: &Path) -> std::io::Result<String> {
    use sha2::{Digest, Sha256};
    let mut files: Vec<PathBuf> = std::fs::read_dir(dir)?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.is_file() && (p.file_name().is_some_and(|n| n == "manifest.json") || p.extension().is_some_and(|x| x == "onnx" || x == "weights")))
        .collect();
    files.sort();
    let mut hash = Sha256::new();
    for f in files {
        hash.update(f.file_name().unwrap_or_default().as_encoded_bytes());
        hash.update(std::fs::read(&f)?);
    }
    Ok(hash.finalize().iter().take(8).map(|b| format!("{b:02x}")).collect())
}

impl Manifest {
    /// Reads and checks `dir/manifest.json`.
    pub fn load(dir: &Path) -> Result<Manifest, ModelError> {
        let path = dir.join("manifest.json");
        let folder_error = |message: String| ModelError::Folder { path: dir.to_path_buf(), message };
        if !dir.is_dir() {
            return Err(folder_error("no such model folder (expected ONNX graphs and manifest.json, e.g. fixtures/small)".into()));
        }
        let text = std::fs::read_to_string(&path)
            .map_err(|e| folder_error(format!("cannot read manifest.json ({e}); is this a folder written by `python -m worldpack_train export`?")))?;
        let mut manifest: Manifest = serde_json::from_str(&text).map_err(|e| ModelError::manifest("manifest.json", e.to_string()))?;
        manifest.validate()?;
        manifest.digest = folder_digest(dir).map_err(|e| folder_error(format!("cannot read its files to digest them: {e}")))?;
        Ok(manifest)
    }

    /// Consistency between fields: shapes, rates and token counts.
    pub fn validate(&self) -> Result<(), ModelError> {
        let bad = |field: &str, message: String| Err(ModelError::manifest(field, message));
        if self.format != FORMAT {
            return bad("format", format!("expected {FORMAT:?}, got {:?}", self.format));
        }
        let a = &self.autoencoder;
        if !(a.latent_scale.is_finite() && a.latent_scale > 0.0) {
            return bad("autoencoder.latent_scale", format!("must be a positive number, got {}", a.latent_scale));
        }
        let latent = [a.latent.channels, a.latent.height, a.latent.width].map(|n| Dim::Fixed(n as i64));
        let image = [self.image.channels, self.image.height, self.image.width].map(|n| Dim::Fixed(n as i64));
        for (field, spec, want) in [
            ("autoencoder.encoder.inputs[0]", a.encoder.inputs.first(), &image),
            ("autoencoder.encoder.outputs[0]", a.encoder.outputs.first(), &latent),
            ("autoencoder.decoder.inputs[0]", a.decoder.inputs.first(), &latent),
            ("autoencoder.decoder.outputs[0]", a.decoder.outputs.first(), &image),
        ] {
            match spec {
                Some(s) if s.shape.len() == 4 && s.shape[1..] == want[..] => {}
                Some(s) => return bad(&format!("{field}.shape"), format!("expected [batch, {:?}], got {:?}", want, s.shape)),
                None => return bad(field, "missing".into()),
            }
        }
        let d = &self.denoiser;
        if d.layouts.is_empty() {
            return bad("denoiser.layouts", "at least one layout is needed".into());
        }
        for (i, layout) in d.layouts.iter().enumerate() {
            let at = format!("denoiser.layouts[{i}]");
            let mut total = 0;
            for (j, slot) in layout.slots.iter().enumerate() {
                if !d.rates.contains(&slot.rate) {
                    return bad(&format!("{at}.slots[{j}].rate"), format!("{} is not one of denoiser.rates {:?}", slot.rate, d.rates));
                }
                let Some(side) = memory::policy::side_factor(slot.rate) else {
                    return bad(&format!("{at}.slots[{j}].rate"), format!("{} is not a square (1, 4, 16, ...)", slot.rate));
                };
                let k = (d.patch * side) as usize;
                let want = (a.latent.height.div_ceil(k) * a.latent.width.div_ceil(k)) as u64;
                if slot.tokens_per_frame != want {
                    return bad(&format!("{at}.slots[{j}].tokens_per_frame"), format!("expected {want}, got {}", slot.tokens_per_frame));
                }
                if slot.count == 0 {
                    return bad(&format!("{at}.slots[{j}].count"), "must be at least 1".into());
                }
                total += slot.count as u64 * want;
            }
            if layout.context_tokens != total {
                return bad(&format!("{at}.context_tokens"), format!("expected {total}, got {}", layout.context_tokens));
            }
            if layout.frames != layout.slots.iter().map(|s| s.count).sum::<usize>() {
                return bad(&format!("{at}.frames"), "must equal the sum of the slot counts".into());
            }
            let noise_inputs = layout.inputs.iter().filter(|i| i.name.starts_with(CONTEXT_NOISE_PREFIX)).count();
            if noise_inputs > 0 && d.context_noise.is_none() {
                return bad("denoiser.context_noise", format!("{at} takes context noise levels, but the manifest does not say which"));
            }
            if noise_inputs != 0 && noise_inputs != layout.slots.len() {
                return bad(&format!("{at}.inputs"), "context noise levels for some rates but not all".into());
            }
            if let Some(w) = &d.warp
                && !layout.inputs.iter().any(|i| i.name == w.input)
            {
                return bad(&format!("{at}.inputs"), format!("denoiser.warp names the input {:?}, which this layout lacks", w.input));
            }
        }
        if let Some(w) = &d.warp {
            if w.frames == 0 {
                return bad("denoiser.warp.frames", "must be at least 1".into());
            }
            if w.channels != a.latent.channels + 1 {
                return bad("denoiser.warp.channels", format!("expected the latent's {} channels plus coverage, got {}", a.latent.channels, w.channels));
            }
            if !self.image.height.is_multiple_of(a.latent.height) || !self.image.width.is_multiple_of(a.latent.width) {
                return bad("denoiser.warp", "the image must be a whole multiple of the latent to pool the coverage".into());
            }
        }
        if let Some(g) = &self.fusion {
            if d.warp.is_none() {
                return bad("fusion", "a fusion head blends the warp of the model's warp sources, but the denoiser takes no warp".into());
            }
            let names: Vec<&str> = g.inputs.iter().map(|t| t.name.as_str()).collect();
            if names != FUSION_INPUTS {
                return bad("fusion.inputs", format!("expected {FUSION_INPUTS:?}, got {names:?}"));
            }
            // The frame shown, and optionally the frame the memory keeps (python: fusion.HeadPair).
            let outputs: Vec<&str> = g.outputs.iter().map(|t| t.name.as_str()).collect();
            if outputs.len() != 1 && outputs != ["image", "kept"] {
                return bad("fusion.outputs", format!("expected one output, or [\"image\", \"kept\"]; got {outputs:?}"));
            }
        }
        let f = &self.diffusion;
        if f.timesteps == 0 {
            return bad("diffusion.timesteps", "must be at least 1".into());
        }
        if !(0.0 < f.beta_start && f.beta_start < f.beta_end && f.beta_end < 1.0) {
            return bad("diffusion.beta_start", format!("need 0 < beta_start < beta_end < 1, got {} and {}", f.beta_start, f.beta_end));
        }
        if f.prediction != "epsilon" {
            return bad("diffusion.prediction", format!("only \"epsilon\" is supported, got {:?}", f.prediction));
        }
        if let Some(d) = &f.distilled {
            let descending = d.timesteps.windows(2).all(|w| w[0] > w[1]);
            if d.timesteps.is_empty() || !descending || d.timesteps[0] >= f.timesteps {
                return bad("diffusion.distilled.timesteps", format!("need strictly descending indices below {}, got {:?}", f.timesteps, d.timesteps));
            }
        }
        Ok(())
    }

    /// The denoiser layout called `name` (`worldpack`, `baseline`, ...).
    pub fn layout(&self, name: &str) -> Option<&LayoutSpec> {
        self.denoiser.layouts.iter().find(|l| l.name == name)
    }

    /// The layout whose slots are `packing`'s tiers in order (rate and count).
    pub fn layout_for_packing(&self, packing: &memory::Packing) -> Option<&LayoutSpec> {
        let want: Vec<(u32, usize)> = packing.tiers().iter().map(|t| (t.rate, t.slots)).collect();
        self.denoiser.layouts.iter().find(|l| l.slots.iter().map(|s| (s.rate, s.count)).collect::<Vec<_>>() == want)
    }
}

