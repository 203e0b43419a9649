"""The committed model export, checked without torch: every ONNX graph in
Python onnxruntime against the PyTorch references written at export time,
the reference samplers against the PyTorch sampling traces, the graphs'
names and shapes against the manifest, and the manifest's own consistency
(also for an SD-VAE-shaped model a user might export)."""

import json
import pathlib

import numpy as np
import onnx
import onnxruntime as ort
import pytest

ROOT = pathlib.Path(__file__).resolve().parent.parent

from worldpack_train.io import manifest as wm  # torch-free modules only
from worldpack_train.core.config import DiffusionConfig
from worldpack_train.core.diffusion import Sampler, Schedule, sample

MODEL = ROOT / "fixtures" / "small"
MANIFEST = json.loads((MODEL / "manifest.json").read_text())
# The trained voxel-world variants and the Doom models (float16-stored weights), checked graph by graph too.
VARIANTS = sorted(p.parent for world in ("variants", "doom", "miniworld") for p in (ROOT / "fixtures" / world).glob("*/manifest.json"))
TOL = MANIFEST["reference"]["tolerance"]


def close(actual, expected, what):
    actual, expected = np.asarray(actual), np.asarray(expected)
    assert actual.shape == expected.shape, f"{what}: shape {actual.shape} != {expected.shape}"
    excess = np.abs(actual - expected) - (TOL["abs"] + TOL["rel"] * np.abs(expected))
    worst = float(excess.max())
    assert worst <= 0, f"{what}: exceeds |a-b| <= {TOL['abs']} + {TOL['rel']}|b| by {worst:.3g}"


def session(file, model=MODEL):
    return ort.InferenceSession(str(model / file), providers=["CPUExecutionProvider"])


def load(folder, model=MODEL):
    return {p.stem: np.load(p) for p in (model / folder).glob("*.npy")}


def graphs(manifest=MANIFEST):
    """(graph name, onnx file, io spec) for every exported graph."""
    ae = manifest["autoencoder"]
    out = [("encoder", ae["encoder"]["file"], ae["encoder"]), ("decoder", ae["decoder"]["file"], ae["decoder"])]
    out += [(f"denoiser_{lay['name']}", lay["file"], lay) for lay in manifest["denoiser"]["layouts"]]
    if "fusion" in manifest:  # a geometry model's fusion head
        out.append(("fusion", manifest["fusion"]["file"], manifest["fusion"]))
    return out


def run_graph(name, file, spec, arrays, model=MODEL):
    feed = {s["name"]: arrays[s["name"]] for s in spec["inputs"]}
    return session(file, model).run(None, feed)


def variant_graphs():
    for model in VARIANTS:
        manifest = json.loads((model / "manifest.json").read_text())
        for name, file, spec in graphs(manifest):
            yield pytest.param(model, manifest, name, file, spec, id=f"{model.parent.name}-{model.name}-{name}")


@pytest.mark.parametrize("model,manifest,name,file,spec", list(variant_graphs()))
def test_variant_graph_matches_pytorch(model, manifest, name, file, spec):
    arrays = load(manifest["reference"]["graphs"][name], model)
    for out_spec, got in zip(spec["outputs"], run_graph(name, file, spec, arrays, model)):
        close(got, arrays[out_spec["name"]], f"{model.name}/{name}.{out_spec['name']}")


def test_variants_store_weights_as_float16():
    for model in VARIANTS:
        manifest = json.loads((model / "manifest.json").read_text())
        if not manifest["denoiser"].get("weights_storage", "").startswith("float16"):
            continue
        proto = onnx.load(str(model / manifest["denoiser"]["layouts"][0]["file"]), load_external_data=False)
        halves = [i for i in proto.graph.initializer if i.data_type == onnx.TensorProto.FLOAT16]
        casts = [n for n in proto.graph.node if n.op_type == "Cast"]
        assert halves and len(casts) >= len(halves), f"{model.name}: float16 storage declared but not found"


PAIRED = [m for m in VARIANTS if "pair" in json.loads((m / "manifest.json").read_text()).get("fusion", {})]


@pytest.mark.parametrize("model", PAIRED, ids=[m.name for m in PAIRED])
def test_a_head_pair_shows_its_shown_model_head(model):
    """fusion.HeadPair as exported: the frame shown is the head of the model
    named `pair.shown` (run from its own folder); the frame kept is another."""
    spec = json.loads((model / "manifest.json").read_text())["fusion"]
    shown_dir = model.parent / spec["pair"]["shown"]["model"]
    arrays = load("reference/fusion", model)
    images = {k: arrays[k] for k in ("predicted", "reference", "landed")}
    if spec["pair"].get("holes"):
        # A warp of 32 frames leaves few holes; a wide one shows what the hole head does there.
        images["landed"] = images["landed"].copy()
        images["landed"][:, :, 40:] = 0
    image, kept = session(spec["file"], model).run(None, images)
    if shown_dir.resolve() == model.resolve():
        # One trained head makes both frames; the frame shown differs from the kept only by the detail rules.
        assert spec["pair"]["shown"]["trained"] == spec["pair"]["kept"]["trained"], f"{model.name}: names itself as its shown model"
        assert (spec["pair"].get("hole_detail") or spec["pair"].get("warp_detail")) and not spec["pair"].get("hole_fill"), \
            f"{model.name}: a pair of one head does nothing"
        alone = kept
    else:
        shown_spec = json.loads((shown_dir / "manifest.json").read_text())["fusion"]
        alone = session(shown_spec["file"], shown_dir).run(None, images)[0]
    if spec["pair"].get("hole_detail"):
        alone = detail_in_holes(alone, images["predicted"], images["landed"], spec["pair"]["hole_detail"])
    if spec["pair"].get("warp_detail"):
        alone = warp_detail_where_agreed(alone, images["reference"], images["landed"], spec["pair"]["warp_detail"])
    if spec["pair"].get("holes"):
        # A third head's luma detail in the warp's holes: beyond the rules' 5x5 reach of a hole the frame
        # shown is as without it; in the holes it moves, and by the same amount in R, G and B.
        landed = images["landed"]
        inside, far = box_mean(landed, 5) > 1 - 1e-6, box_mean(landed, 7) == 0
        assert inside.any() and far.any(), f"{model.name}: its reference warp has no holes or no landed pixels"
        moved = image - alone
        assert float(np.abs(np.where(inside, moved, 0)).max()) < 1e-5, \
            f"{model.name}: where the warp landed the frame shown is not {shown_dir.name}'s head's with its rules"
        assert float(np.abs(np.where(far, moved, 0)).max()) > 0.01, f"{model.name}: the hole head changed nothing in the holes"
        assert float(np.abs(np.where(far, moved - moved[:, :1], 0)).max()) < 1e-5, \
            f"{model.name}: the hole head changed the colours in the holes, not only their luma"
        return
    assert float(np.abs(image - alone).max()) < 1e-5, f"{model.name}: the frame shown is not {shown_dir.name}'s head's with its rules"
    assert float(np.abs(kept - image).max()) > 0.01, f"{model.name}: the frame kept is the frame shown"


def box_mean(x, k):
    """The k x k mean of NCHW `x` over the pixels inside the frame (fusion.py's
    avg_pool2d with count_include_pad=False)."""
    r = k // 2
    padded = np.pad(x, ((0, 0), (0, 0), (r, r), (r, r)))
    inside = np.pad(np.ones_like(x[:1, :1]), ((0, 0), (0, 0), (r, r), (r, r)))
    total = sum(padded[:, :, i:i + x.shape[2], j:j + x.shape[3]] for i in range(k) for j in range(k))
    count = sum(inside[:, :, i:i + x.shape[2], j:j + x.shape[3]] for i in range(k) for j in range(k))
    return total / count


def detail_in_holes(frame, predicted, landed, k):
    """fusion.detail_in_holes, written again without torch."""
    return frame + ((predicted - box_mean(predicted, k)) - (frame - box_mean(frame, k))) * (1 - landed)


def luma(x):
    """Rec. 601 luma of NCHW RGB `x`, (N, 1, H, W), as fusion.py's."""
    return (x * np.array([0.299, 0.587, 0.114], np.float32).reshape(1, 3, 1, 1)).sum(1, keepdims=True)


def luma_detail(x):
    """What the 3x3 local mean leaves of `x`'s luma: the detail fusion.py's rules move."""
    return luma(x) - box_mean(luma(x), 3)


def warp_detail_where_agreed(frame, reference, landed, tolerance):
    """fusion.warp_detail_where_agreed, written again without torch."""
    distance2 = ((box_mean(reference, 5) - box_mean(frame, 5)) ** 2).sum(1, keepdims=True) * 127.5**2
    agree = np.exp(-np.log(2) * distance2 / tolerance**2)
    return frame + (luma_detail(reference) - luma_detail(frame)) * agree * landed


def hole_case(model, rule, landed_rows):
    """A head pair's manifest entry, its setting for `rule` (hole_fill or
    hole_detail: a window; warp_detail: a tolerance), the frame size, and a
    warp that landed on the top rows only."""
    spec = json.loads((model / "manifest.json").read_text())["fusion"]
    h, w = spec["inputs"][0]["shape"][2:]
    landed = np.zeros((1, 1, h, w), np.float32)
    landed[:, :, :landed_rows] = 1
    return spec, spec["pair"][rule], (h, w), landed


DETAILED = [m for m in PAIRED if json.loads((m / "manifest.json").read_text())["fusion"]["pair"].get("hole_detail")]
HOLE_HEADED = [m for m in PAIRED if json.loads((m / "manifest.json").read_text())["fusion"]["pair"].get("holes")]


@pytest.mark.parametrize("model", HOLE_HEADED, ids=[m.name for m in HOLE_HEADED])
def test_a_hole_head_paints_detail_where_the_warp_has_none(model):
    """fusion.luma_detail_in_holes as exported, on the model's reference
    frames with a wide hole (rows 40 on): there the frame shown carries more
    than 2.5 times the luma gradient energy of the frame kept, the head
    trained for MSE, which paints the mean of what could be there (measured
    when written: 3.1 for the Doom pair; 2.0 for the pair before it, which
    took the decoded frame's detail there)."""
    spec = json.loads((model / "manifest.json").read_text())["fusion"]
    arrays = load("reference/fusion", model)
    images = {k: arrays[k] for k in ("predicted", "reference", "landed")}
    images["landed"] = images["landed"].copy()
    images["landed"][:, :, 40:] = 0
    image, kept = session(spec["file"], model).run(None, images)
    hole = lambda x: luma(x)[:, 0, 42:, :]
    energy = lambda x: float((np.diff(hole(x), axis=2) ** 2).mean() + (np.diff(hole(x), axis=1) ** 2).mean())
    assert energy(image) > 2.5 * energy(kept), \
        f"{model.name}: in the hole the frame shown has {energy(image) / energy(kept):.2f} times the frame kept's edge energy"


@pytest.mark.parametrize("model", DETAILED, ids=[m.name for m in DETAILED])
def test_a_head_pairs_hole_detail_keeps_the_decoded_texture_in_holes(model):
    """fusion.detail_in_holes as exported: a decoded frame with a fine
    checkerboard (+-0.3) where the warp has no pixels (rows 32 on). In the
    hole the frame shown differs from the decoded frame by the head's and
    the decoded frame's local means only, which carry almost none of the
    checkerboard: it keeps all but 0.02 of it (measured when written: 0.006
    for the Doom model's pair; its head alone, the frame kept, loses 0.054).
    A pair with a hole head takes that head's luma detail there, so its
    checkerboard is one of colour alone (no luma), which it keeps the same
    (measured when written, the Doom pair: 0.008; a luma checkerboard 0.030)."""
    spec, k, (h, w), landed = hole_case(model, "hole_detail", landed_rows=32)
    reference = np.full((1, 3, h, w), 0.1, np.float32)
    sign = (np.indices((h, w)).sum(0) % 2 * 2 - 1).astype(np.float32)
    # Red against green at their luma weights' ratio: 0.299 * 0.587 - 0.587 * 0.299 = 0.
    colour = np.array([0.587, -0.299, 0.0] if spec["pair"].get("holes") else [1.0, 1.0, 1.0], np.float32)
    colour /= np.abs(colour).max()
    pattern = 0.3 * sign * (np.arange(h)[:, None] >= 32)
    predicted = (-0.2 + colour.reshape(1, 3, 1, 1) * pattern).astype(np.float32)
    image, _ = session(spec["file"], model).run(None, {"predicted": predicted, "reference": reference, "landed": landed})
    hole = (slice(None), slice(None), slice(32 + k, h - k), slice(k, w - k))
    along = colour.reshape(1, 3, 1, 1) / float((colour**2).sum())  # the checkerboard's share, channel by channel
    lost = float((((image - predicted) * along).sum(1)[0] * sign)[hole[2:]].mean())
    assert abs(lost) < 0.02, f"{model.name}: the frame shown lost {-lost:.3f} of the decoded frame's 0.3 checkerboard in the hole"


WARP_DETAILED = [m for m in PAIRED if json.loads((m / "manifest.json").read_text())["fusion"]["pair"].get("warp_detail")]
# Pairs whose frame shown, where the warp landed, is the kept head's frame with the rule.
WARP_DETAILED_ON_KEPT = [m for m in WARP_DETAILED
                         if json.loads((m / "manifest.json").read_text())["fusion"]["pair"]["shown"]["model"] == m.name]


@pytest.mark.parametrize("model", WARP_DETAILED, ids=[m.name for m in WARP_DETAILED])
def test_a_head_pairs_warp_detail_brings_the_warps_detail_on_real_frames(model):
    """fusion.warp_detail_where_agreed as exported, on the model's reference
    frames: where the warp landed, the luma detail (beyond a 3x3 mean) of the
    frame shown is nearer the warp's than that of the frame the pair shows
    without the rule; beyond the rule's 5x5 reach of the warp, nothing moves."""
    spec = json.loads((model / "manifest.json").read_text())["fusion"]
    arrays = load("reference/fusion", model)
    images = {k: arrays[k] for k in ("predicted", "reference", "landed")}
    image, kept = session(spec["file"], model).run(None, images)
    if spec["pair"]["shown"]["model"] == model.name:
        alone = kept
    else:
        shown_dir = model.parent / spec["pair"]["shown"]["model"]
        alone = session(json.loads((shown_dir / "manifest.json").read_text())["fusion"]["file"], shown_dir).run(None, images)[0]
    if spec["pair"].get("hole_detail"):
        alone = detail_in_holes(alone, images["predicted"], images["landed"], spec["pair"]["hole_detail"])
    landed = images["landed"] > 0.5
    gap = lambda x: float(np.abs(luma_detail(x) - luma_detail(images["reference"]))[landed].mean())
    assert gap(image) < 0.9 * gap(alone), \
        f"{model.name}: where the warp landed the frame shown's detail is {gap(image):.4f} from the warp's, without the rule {gap(alone):.4f}"
    if not spec["pair"].get("holes"):  # a hole head moves those pixels on purpose
        far = box_mean(images["landed"], 7) == 0
        assert float(np.abs(np.where(far, image - alone, 0)).max()) < 1e-5, f"{model.name}: the rule moved pixels far from the warp"


@pytest.mark.parametrize("model", WARP_DETAILED_ON_KEPT, ids=[m.name for m in WARP_DETAILED_ON_KEPT])
def test_a_head_pairs_warp_detail_keeps_the_warps_texture_only_where_it_agrees(model):
    """fusion.warp_detail_where_agreed as exported: the warp landed on the
    top 32 rows with a fine checkerboard (+-0.3). On the left half its local
    mean is the decoded frame's, and the frame shown keeps more of the
    checkerboard than its head alone (the frame kept; measured when written,
    Doom's pair: 0.54 against 0.475 at 2 levels' tolerance, 0.73 at 6); on
    the right half it is 0.5 brighter (64 8-bit levels, far past any
    tolerance), a warp on the wrong surface, and the frame shown keeps what
    the head alone keeps (0.285). (The voxel pair's head for the frame
    shown, trained for MSE on voxel frames, sits 10-16 levels darker than
    this synthetic warp, past the tolerance, so it is checked on real frames
    above only.)"""
    spec, _, (h, w), landed = hole_case(model, "warp_detail", landed_rows=32)
    sign = (np.indices((h, w)).sum(0) % 2 * 2 - 1).astype(np.float32)
    offset = np.where(np.arange(w) >= w // 2, 0.5, 0.0).astype(np.float32)[None, :]
    reference = np.broadcast_to(-0.2 + offset + 0.3 * sign, (1, 3, h, w)).astype(np.float32)
    predicted = np.full((1, 3, h, w), -0.2, np.float32)
    image, kept = session(spec["file"], model).run(None, {"predicted": predicted, "reference": reference, "landed": landed})
    share = lambda frame, cols: float((frame[:, :, 4:28, cols] * sign[4:28, cols]).mean()) / 0.3
    left, right = slice(4, w // 2 - 6), slice(w // 2 + 6, w - 4)
    assert share(image, left) > share(kept, left) + 0.05, \
        f"{model.name}: where the warp agrees the frame shown kept {share(image, left):.3f} of its texture, the head alone {share(kept, left):.3f}"
    assert abs(share(image, right) - share(kept, right)) < 0.01, \
        f"{model.name}: where the warp is 64 levels off the frame shown kept {share(image, right):.3f}, the head alone {share(kept, right):.3f}"


FILLED = [m for m in PAIRED if json.loads((m / "manifest.json").read_text())["fusion"]["pair"].get("hole_fill")]


@pytest.mark.parametrize("model", FILLED, ids=[m.name for m in FILLED])
def test_a_head_pairs_hole_fill_keeps_a_bright_ground_bright(model):
    """fusion.fill_holes_from_warp as exported: a bright ground that the warp
    reached down to row 40, a darker guess below it. Within K // 2 rows of
    the landed ground the kept frame takes the ground's brightness; deeper in
    the hole it stays the head's (the own head alone keeps the band as dark
    as the rows below it)."""
    spec, k, (h, w), landed = hole_case(model, "hole_fill", landed_rows=40)
    reference = np.full((1, 3, h, w), 0.8, np.float32)
    reference[:, :, 40:] = -0.6  # the fused reference's unlanded pixels are not the world's: the fill must not use them
    predicted = np.full((1, 3, h, w), 0.8, np.float32)
    predicted[:, :, 40:] = -0.2
    _, kept = session(spec["file"], model).run(None, {"predicted": predicted, "reference": reference, "landed": landed})
    band, deeper = float(kept[0, :, 40:40 + k // 2].mean()), float(kept[0, :, 40 + k // 2 + 2:].mean())
    assert band > deeper + 0.4, f"{model.name}: the band next to the landed ground ({band:.2f}) is not brighter than deeper ({deeper:.2f})"


@pytest.mark.parametrize("name,file,spec", graphs(), ids=[g[0] for g in graphs()])
def test_graph_matches_pytorch(name, file, spec):
    arrays = load(MANIFEST["reference"]["graphs"][name])
    outputs = run_graph(name, file, spec, arrays)
    for out_spec, got in zip(spec["outputs"], outputs):
        close(got, arrays[out_spec["name"]], f"{name}.{out_spec['name']}")


@pytest.mark.parametrize("name,file,spec", graphs(), ids=[g[0] for g in graphs()])
def test_graph_io_matches_manifest(name, file, spec):
    model = onnx.load(str(MODEL / file), load_external_data=False)
    assert model.ir_version <= 10, f"{file}: IR version {model.ir_version}; ONNX Runtime 1.31 needs <= 10 here"
    sess = session(file)
    for declared, actual in ((spec["inputs"], sess.get_inputs()), (spec["outputs"], sess.get_outputs())):
        assert [d["name"] for d in declared] == [a.name for a in actual], file
        for d, a in zip(declared, actual):
            fixed = [x if isinstance(x, int) else None for x in d["shape"]]
            got = [x if isinstance(x, int) else None for x in a.shape]
            assert fixed == got, f"{file}: {d['name']} shape {a.shape}, manifest says {d['shape']}"
            assert a.type == "tensor(float)", f"{file}: {d['name']} is {a.type}"


def test_batch_is_dynamic_and_rows_independent():
    lay = MANIFEST["denoiser"]["layouts"][0]
    arrays = load(MANIFEST["reference"]["graphs"][f"denoiser_{lay['name']}"])
    one = run_graph("", lay["file"], lay, {k: v[1:2] for k, v in arrays.items()})[0]
    close(one, arrays["eps"][1:2], "second row run alone")


def test_empty_slots_are_ignored_and_present_ones_are_not():
    """A masked slot's contents cannot change eps; a present slot's must."""
    lay = next(x for x in MANIFEST["denoiser"]["layouts"] if len(x["slots"]) > 1)
    arrays = load(MANIFEST["reference"]["graphs"][f"denoiser_{lay['name']}"])
    sess = session(lay["file"])
    feed = {s["name"]: arrays[s["name"]].copy() for s in lay["inputs"]}
    r = lay["slots"][-1]["rate"]
    feed[f"context_mask_r{r}"][:, -1] = 0.0
    base = sess.run(None, feed)[0]
    feed[f"context_r{r}"][:, -1] += 5.0
    feed[f"context_pose_r{r}"][:, -1] += 1.0
    close(sess.run(None, feed)[0], base, "eps after changing a masked slot")
    r1 = lay["slots"][0]["rate"]
    feed[f"context_r{r1}"][:, 0] += 1.0
    changed = np.abs(sess.run(None, feed)[0] - base).max()
    assert changed > 1e-3, f"changing a present slot moved eps by only {changed}"


def test_rate_slots_cost_the_manifest_tokens():
    for lay in MANIFEST["denoiser"]["layouts"]:
        assert lay["context_tokens"] == sum(s["count"] * s["tokens_per_frame"] for s in lay["slots"])
    packed = next(x for x in MANIFEST["denoiser"]["layouts"] if x["name"] == "worldpack")
    base = next(x for x in MANIFEST["denoiser"]["layouts"] if x["name"] == "baseline")
    assert packed["frames"] == 22 and base["frames"] == 4
    assert packed["context_tokens"] == base["context_tokens"], "the packed 22 frames must fit the 4-frame budget"


@pytest.mark.parametrize("method", sorted(MANIFEST["reference"]["traces"]))
def test_sampler_trace_matches_pytorch(method):
    """Each step from the reference state, with ONNX Runtime as the denoiser and
    the NumPy reference sampler, lands on PyTorch's next state."""
    info = MANIFEST["reference"]["traces"][method]
    trace = load(info["folder"])
    lay = next(x for x in MANIFEST["denoiser"]["layouts"] if x["name"] == info["layout"])
    cond = load(MANIFEST["reference"]["graphs"][f"denoiser_{lay['name']}"])
    sess = session(lay["file"])
    names = [s["name"] for s in lay["inputs"]]
    schedule = Schedule(DiffusionConfig(**{k: MANIFEST["diffusion"][k] for k in ("timesteps", "beta_start", "beta_end")}))
    sampler = Sampler(schedule, info["steps"], method, info["eta"])
    assert list(sampler.timesteps) == list(trace["timesteps"])
    for i, t in enumerate(sampler.timesteps):
        feed = {n: cond[n] for n in names}
        feed["x_t"] = trace["x"][i]
        feed["timestep"] = np.full(trace["x"].shape[1], t, np.float32)
        eps = sess.run(None, feed)[0]
        close(eps, trace["eps"][i], f"{method} step {i} eps")
        close(sampler.step(i, trace["x"][i], eps, trace["noise"][i]), trace["x"][i + 1], f"{method} step {i} state")


@pytest.mark.parametrize("method", ["ancestral", "ddim"])
def test_samplers_recover_x0_from_an_oracle(method):
    """With the true noise as the model's answer, both samplers land on x0."""
    schedule = Schedule(DiffusionConfig())
    rng = np.random.default_rng(0)
    x0 = rng.standard_normal((2, 4, 8, 8)).astype(np.float32)
    ab = schedule.alphas_cumprod
    oracle = lambda x, t: ((x - np.sqrt(ab[int(t[0])]) * x0) / np.sqrt(1 - ab[int(t[0])])).astype(np.float32)
    x_T = (np.sqrt(ab[-1]) * x0 + np.sqrt(1 - ab[-1]) * rng.standard_normal(x0.shape)).astype(np.float32)
    trace = sample(oracle, schedule, x_T, 12, method)
    assert trace.timesteps[0] == 999 and trace.timesteps[-1] == 0
    np.testing.assert_allclose(trace.x[-1], x0, atol=1e-5)


def test_committed_manifest_is_consistent():
    assert wm.validate(MANIFEST) == []


def test_warp_frames_sets_the_served_count_and_keeps_the_trained_one(tmp_path):
    """`model.sh warp-frames`: only the manifest's warp count changes; a model without the warp input is refused."""
    geometry = tmp_path / "geometry"
    geometry.mkdir()
    source = json.loads((ROOT / "fixtures" / "variants" / "worldpack_geometry" / "manifest.json").read_text())
    (geometry / "manifest.json").write_text(json.dumps(source))
    wm.set_warp_frames(geometry, 12)
    changed = json.loads((geometry / "manifest.json").read_text())
    assert changed["denoiser"]["warp"]["frames"] == 12 and changed["denoiser"]["warp"]["trained_frames"] == "1 to 3"
    changed["denoiser"]["warp"] = source["denoiser"]["warp"]
    assert changed == source, "nothing else in the manifest moves"
    assert wm.validate(json.loads((geometry / "manifest.json").read_text())) == []
    with pytest.raises(SystemExit, match="--frames"):
        wm.set_warp_frames(geometry, 0)
    plain = tmp_path / "plain"
    plain.mkdir()
    (plain / "manifest.json").write_text((ROOT / "fixtures" / "variants" / "baseline" / "manifest.json").read_text())
    with pytest.raises(SystemExit, match="no warp input"):
        wm.set_warp_frames(plain, 8)


def test_sd_vae_shaped_manifest_is_accepted():
    """A CDiT-B/2 over the SD VAE (28x28x4 latents, scale 0.18215) at rates 1/4/16."""
    example = json.loads((ROOT / "fixtures" / "examples" / "sd-vae-cdit-b2.manifest.json").read_text())
    assert wm.validate(example) == []
    slots = {s["rate"]: s["tokens_per_frame"] for s in example["denoiser"]["layouts"][0]["slots"]}
    assert slots == {1: 196, 4: 49, 16: 16}, "28/2=14, 28/4=7, 28/8 -> replicate-padded to 4 per side"


def test_paper_token_geometry_fixture_is_consistent():
    """The committed paper-token model (random weights) has the example's token geometry, graphs and all."""
    m = json.loads((ROOT / "fixtures" / "paper_tokens" / "manifest.json").read_text())
    assert wm.validate(m) == []
    layouts = {x["name"]: x for x in m["denoiser"]["layouts"]}
    assert {s["rate"]: s["tokens_per_frame"] for s in layouts["worldpack"]["slots"]} == {1: 196, 4: 49, 16: 16}
    assert (layouts["worldpack"]["context_tokens"], layouts["baseline"]["context_tokens"]) == (844, 784)
    assert "training" not in m and "metrics" not in m, "random weights claim no training and no accuracy"


@pytest.mark.parametrize("path,value,expect", [
    ("autoencoder.latent_scale", -1.0, "autoencoder.latent_scale"),
    ("denoiser.layouts.0.slots.1.tokens_per_frame", 15, "denoiser.layouts[0].slots[1].tokens_per_frame"),
    ("denoiser.layouts.0.slots.1.rate", 3, "denoiser.layouts[0].slots[1].rate"),
    ("diffusion.beta_end", 1e-5, "diffusion.beta_start/beta_end"),
    ("format", "other/1", "format"),
])
def test_bad_manifests_name_the_field(path, value, expect):
    bad = json.loads(json.dumps(MANIFEST))
    node = bad
    parts = path.split(".")
    for p in parts[:-1]:
        node = node[int(p)] if p.isdigit() else node[p]
    node[parts[-1]] = value
    errors = wm.validate(bad)
    assert any(e.startswith(expect) for e in errors), errors
