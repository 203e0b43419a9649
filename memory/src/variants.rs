//! Every named context policy in one table: the paper's presets, the
//! look-ahead (target-pose) options of the scored ones, and the trained
//! variants' weights. Plans, training, evaluation and reports take names and
//! labels from here, so a new policy is one row.

use crate::error::InputError;
use crate::policy::{Policy, PolicyKind, Query};

#[derive(Debug)]
pub struct Variant {
    /// As users and files write it (`worldpack`, `plan-worldpack.npy`, `fixtures/variants/worldpack`).
    pub name: &'static str,
    /// As tables show it.
    pub label: &'static str,
    /// As a chart's point labels show it.
    pub short: &'static str,
    pub kind: PolicyKind,
    pub query: Query,
    pub keep_last: bool,
    /// The trained weights it runs with: a variant folder's name.
    pub weights: &'static str,
}

impl Variant {
    pub fn policy(&self) -> Policy {
        Policy { query: self.query, keep_last: self.keep_last, ..Policy::preset(self.kind) }
    }
}

const fn row(name: &'static str, label: &'static str, short: &'static str, kind: PolicyKind, query: Query, keep_last: bool, weights: &'static str) -> Variant {
    Variant { name, label, short, kind, query, keep_last, weights }
}

/// In the paper's order, then WorldMem's, then the look-ahead options.
pub const VARIANTS: &[Variant] = &[
    row("baseline", "Baseline (4 newest)", "baseline", PolicyKind::Baseline, Query::Target, false, "baseline"),
    row("nearest_frame_packing", "Nearest frame packing", "NFP", PolicyKind::NearestFramePacking, Query::Target, false, "nearest_frame_packing"),
    row("memory_retrieval", "Memory retrieval", "MR", PolicyKind::MemoryRetrieval, Query::Current, false, "memory_retrieval"),
    row("worldpack", "WorldPack", "WorldPack", PolicyKind::WorldPack, Query::Current, false, "worldpack"),
    // WorldMem's greedy selection fills four full-rate slots, like memory retrieval, so it borrows those weights.
    row("worldmem_greedy", "WorldMem greedy", "WorldMem greedy", PolicyKind::WorldMemGreedy, Query::Target, false, "memory_retrieval"),
    // The target-pose query at inference, with the weights trained on the current-pose query's plans.
    row("memory_retrieval_target", "Memory retrieval, target-pose query", "MR target", PolicyKind::MemoryRetrieval, Query::Target, false, "memory_retrieval"),
    row("worldpack_target", "WorldPack, target-pose query", "WP target", PolicyKind::WorldPack, Query::Target, false, "worldpack"),
    // The fix of 2026-11-21 for the target-pose query dropping the newest frame;
    // Algorithm 1 keeps that frame by itself, so this stays only for the models trained so.
    row("worldpack_keep_last", "WorldPack, target-pose query, newest kept", "keep-last", PolicyKind::WorldPack, Query::Target, true, "worldpack_keep_last"),
];

/// The variant called `name`; the error lists the names.
pub fn variant(name: &str) -> Result<&'static Variant, InputError> {
    VARIANTS.iter().find(|v| v.name == name).ok_or_else(|| {
        let names: Vec<&str> = VARIANTS.iter().map(|v| v.name).collect();
        InputError::invalid("policy", format!("unknown policy {name:?}; one of {}", names.join(", ")))
    })
}

/// How a chart labels a row named `name`: a variant's short label, or a
/// variant's row with a setting after a comma (`worldpack, 4 steps` →
/// `WorldPack 4 steps`, `Monte Carlo` as `MC`), or the name itself.
pub fn short_label(name: &str) -> String {
    if let Ok(v) = variant(name) {
        return v.short.to_string();
    }
    match name.split_once(", ") {
        Some((head, rest)) if variant(head).is_ok() => format!("{} {}", variant(head).map_or(head, |v| v.short), rest.replace("Monte Carlo ", "MC ")),
        _ => name.to_string(),
    }
}

/// The name of the variant `policy` is (same kind, query and pinning), if any.
pub fn name_of(policy: &Policy) -> Option<&'static str> {
    VARIANTS.iter().find(|v| v.kind == policy.kind && v.query == policy.query && v.keep_last == policy.keep_last).map(|v| v.name)
}

impl PolicyKind {
    /// The preset's name (`worldpack`, `memory_retrieval`, ...).
    pub fn name(self) -> &'static str {
        name_of(&Policy::preset(self)).expect("every preset is a row of VARIANTS")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_are_unique_and_round_trip() {
        for (i, v) in VARIANTS.iter().enumerate() {
            assert!(VARIANTS[..i].iter().all(|w| w.name != v.name), "{} twice", v.name);
            assert_eq!(name_of(&v.policy()), Some(v.name));
            assert_eq!(variant(v.name).unwrap().name, v.name);
        }
        for kind in [PolicyKind::Baseline, PolicyKind::NearestFramePacking, PolicyKind::MemoryRetrieval, PolicyKind::WorldPack, PolicyKind::WorldMemGreedy] {
            // The serde name users write in a policy spec is the registry's.
            assert_eq!(serde_json::to_value(kind).unwrap(), kind.name());
        }
        assert_eq!(short_label("nearest_frame_packing"), "NFP");
        assert_eq!(short_label("worldpack_keep_last, 4 steps"), "keep-last 4 steps");
        assert_eq!(short_label("worldpack, Monte Carlo 1000"), "WorldPack MC 1000");
        assert_eq!(short_label("worldpack_tiny"), "worldpack_tiny");
        let err = variant("bogus").unwrap_err();
        assert_eq!(err.field(), "policy");
        assert!(err.to_string().contains("worldpack_target"), "{err}");
    }

    #[test]
    fn every_variant_runs_with_weights_that_ship() {
        let shipped = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../fixtures/variants");
        for v in VARIANTS {
            assert!(shipped.join(v.weights).join("manifest.json").exists(), "{}: no fixtures/variants/{}", v.name, v.weights);
        }
    }
}
