"""fixtures/ holds what runs: every model folder is a shipped model with its card
(MODEL.md), or something a test loads by name. Research models are made by their scripts'
commands instead of being kept in the tree."""

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
# The tests, the product's code (the binary's crates, the trainer's families) and the shipped
# manifests (a head pair names the model its shown head came from; the parity test loads it).
LOADERS = [p for pattern in ("tests/**/*.py", "tests/**/*.rs", "*/tests/**/*.rs", "*/src/**/*.rs", "train/worldpack_train/**/*.py",
                             "fixtures/**/manifest.json")
           for p in ROOT.glob(pattern) if "target" not in p.parts]


def model_folders() -> list[Path]:
    return sorted(p.parent for p in (ROOT / "fixtures").rglob("manifest.json") if "reference" not in p.parts)


def loaded_by_name(folder: Path) -> bool:
    """Named by its path under fixtures/ (`variants/worldpack`), or quoted by its own name."""
    rel = folder.relative_to(ROOT / "fixtures").as_posix()
    pattern = re.compile(re.escape(rel) + r"\b|\"" + re.escape(folder.name) + r"\"")
    return any(pattern.search(p.read_text(errors="ignore")) for p in LOADERS if p.parent != folder)


def test_every_model_folder_has_a_card_or_code_that_loads_it():
    orphans = [f.relative_to(ROOT).as_posix() for f in model_folders()
               if not (f / "MODEL.md").exists() and not loaded_by_name(f)]
    assert not orphans, f"model folders nothing runs (give them a card, a test, or remove them): {orphans}"


def test_the_shipped_served_models_carry_their_cards():
    for served in ("fixtures/variants/worldpack_geometry_fused_1step", "fixtures/doom/geometry_fused",
                   "fixtures/miniworld/geometry_fused"):
        card = ROOT / served / "MODEL.md"
        assert card.exists(), f"{served}: no MODEL.md"
        assert "## Served as" in card.read_text() and "PSNR dB" in card.read_text()
