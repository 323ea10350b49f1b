"""Typed settings (mogaf.settings): each default defined once, checked, documented."""

from __future__ import annotations

import dataclasses
import re
from typing import Literal

import pytest

from mogaf import settings
from mogaf.config import with_defaults
from mogaf.errors import MogafError
from support.paths import REPO


@dataclasses.dataclass(frozen=True)
class Toy:
    steps: int = settings.setting(10, "ours", minimum=1)
    rate: float = settings.setting(0.5, "paper", exclusive_minimum=0, exclusive_maximum=1)
    mode: Literal["a", "b"] = settings.setting("a")
    flag: bool = settings.setting(True)
    limit: int | None = settings.setting(None)
    sizes: list = settings.setting([1, 2])
    seed: int = settings.setting(0, injected=True)


def test_defaults_are_fresh_copies():
    first = settings.defaults(Toy)
    first["sizes"].append(3)
    assert settings.defaults(Toy)["sizes"] == [1, 2]
    assert list(first) == ["steps", "rate", "mode", "flag", "limit", "sizes", "seed"]


def test_check_fills_converts_and_refuses():
    out = settings.check(Toy, "toy", {"steps": 4.0, "limit": None})
    assert out["steps"] == 4 and type(out["steps"]) is int and out["limit"] is None
    assert out["rate"] == 0.5 and out["mode"] == "a" and out["seed"] == 0
    for bad, words in [
        ({"step": 1}, "unknown parameter(s) step"),
        ({"steps": 0}, "'steps' must be at least 1"),
        ({"steps": 1.5}, "'steps' must be an integer"),
        ({"rate": 0}, "greater than 0"),
        ({"rate": 1.0}, "less than 1"),
        ({"mode": "c"}, "one of a, b"),
        ({"flag": 1}, "true or false"),
        ({"sizes": "x"}, "must be a list"),
        ({"steps": True}, "must be an integer"),
    ]:
        with pytest.raises(MogafError, match=words.replace("(", r"\(").replace(")", r"\)")):
            settings.check(Toy, "toy", bad)
    with pytest.raises(MogafError, match="must be a mapping"):
        settings.check(Toy, "toy", ["steps"])


def test_load_gives_a_frozen_instance():
    toy = settings.load(Toy, "toy", {"steps": 3})
    assert toy.steps == 3 and toy.mode == "a"
    with pytest.raises(dataclasses.FrozenInstanceError):
        toy.steps = 4


def test_section_schema_follows_the_fields():
    schema = settings.section_schema(Toy)
    props = schema["properties"]
    assert schema["additionalProperties"] is False and "seed" not in props
    assert props["steps"] == {"type": "integer", "minimum": 1, "description": "ours"}
    assert props["rate"]["exclusiveMinimum"] == 0 and props["rate"]["exclusiveMaximum"] == 1
    assert props["mode"]["enum"] == ["a", "b"] and props["limit"]["type"] == ["integer", "null"]
    assert props["sizes"]["type"] == "array"


@pytest.mark.parametrize("path", list(settings.SECTIONS))
def test_every_setting_has_a_source_and_a_schema(path):
    cls = settings.section_class(path)
    assert dataclasses.is_dataclass(cls) and cls.__dataclass_params__.frozen
    schema = settings.section_schema(cls)
    for name, _default, source in settings.describe(cls):
        field = next(f for f in dataclasses.fields(cls) if f.name == name)
        if field.metadata.get("injected"):
            continue
        assert source, f"{path}.{name} has no source"
        assert name in schema["properties"]
    # the defaults pass their own check
    assert settings.check(cls, path, {}) == settings.defaults(cls)


# A setting's source says what it means and why this default, in at most two
# sentences; measurements, dates and experiment history belong in the git log.
_ABBREVIATIONS = ("e.g.", "i.e.", "etc.", "vs.", "cf.", "approx.", "supp.", "sec.", "fig.", "eq.", "no.")
_DATE = re.compile(r"\b\d{4}-\d{2}-\d{2}\b")
_SCORE = re.compile(
    r"\bmeasured\b"  # "measured worse", "measured: ..."
    r"|\d\s*dB\b"  # "21.42 dB", "+0.07 dB"
    r"|\b(?:m?PSNR|LPIPS|SSIM|EPE|ARI|AJ)\s*[-+]?\d"  # "ARI 0.10", "LPIPS -0.0021"
    r"|\d\.\d+\s*(?:->|against)\s*[-+]?\d"  # "1.55 -> 0.39 m", "0.059 against 0.049"
    r"|~\s*\d+(?:\.\d+)?\s*s\b"  # "~20 s CPU"
    r"|\b\d+(?:\.\d+)?x\s+(?:slower|faster|more|less|better|worse)\b",  # "~3x slower"
    re.IGNORECASE,
)


def _sentences(text: str) -> list[str]:
    """`text` split at a full stop (or ! ?) followed by a space or the end; the
    dots of abbreviations and of numbers (0.25, x 0.25, "0." at the end) do not split."""
    masked = text
    for abbreviation in _ABBREVIATIONS:
        masked = re.sub(re.escape(abbreviation), abbreviation.replace(".", "\0"), masked, flags=re.IGNORECASE)
    return [part for part in re.split(r"[.!?]+(?:\s+|$)", masked.strip()) if part.strip(" \0")]


def test_sentence_counter_ignores_abbreviations_and_numbers():
    assert len(_sentences("weight, e.g. 0.25 x the extent; i.e. small")) == 1
    assert len(_sentences("lr x 0.25 (supp. Sec. 3.1), cf. SoM vs. ours, etc. and more.")) == 1
    assert len(_sentences("--dropout 0.")) == 1
    assert len(_sentences("SoM: 0.1. CPU: fewer steps")) == 2
    assert len(_sentences("what it is. why. history")) == 3
    assert _SCORE.search("held-out 21.4 -> 24.2 dB") and _SCORE.search("ARI 0.10 -> 0.48")
    assert _DATE.search("the candidates (2026-11-25)")
    assert not _SCORE.search('"window 10 -> 1"') and not _SCORE.search("linear 40% -> 0% over the first half")


@pytest.mark.parametrize("path", list(settings.SECTIONS))
def test_every_source_is_what_and_why_without_measurements(path):
    cls = settings.section_class(path)
    for name, _default, source in settings.describe(cls):
        where = f"{path}.{name}: {source!r}"
        assert len(_sentences(source)) <= 2, f"more than two sentences in {where}"
        assert not _DATE.search(source), f"a date in {where}"
        score = _SCORE.search(source)
        assert score is None, f"a measurement ({score and score.group(0)!r}) in {where}"


def test_with_defaults_fills_every_section_and_keeps_given_values():
    cfg = with_defaults({"recon": {"iterations": 7}, "forecast": {"methods": ["frozen"]}})
    assert cfg["recon"]["iterations"] == 7 and cfg["recon"]["num_bases"] == 10
    assert cfg["forecast"]["methods"] == ["frozen"] and cfg["forecast"]["mogaf"]["structured"]["context"] == 16
    assert "seed" not in cfg["priors"] and "device" not in cfg["recon"]


def test_config_readme_is_current():
    text = (REPO / "config" / "README.md").read_text()
    assert text.strip() == settings.markdown().strip(), "run: python -m mogaf.settings --markdown > config/README.md"


def test_the_config_schema_and_defaults_load_no_stage_code():
    """Every workflow and CLI start builds the schema and the defaults from the
    settings classes: that must not import torch, OpenCV or scikit-learn (a
    stage package's __init__ imports only its params; its entry points are
    imported from their modules)."""
    import subprocess
    import sys

    code = (
        "import sys; from mogaf.schema import load_config_schema; from mogaf.config import with_defaults, load_yaml; "
        f"load_config_schema({str(REPO / 'config' / 'schema.yaml')!r}); "
        f"with_defaults(load_yaml({str(REPO / 'config' / 'config.yaml')!r})); "
        "print(sorted(m for m in ('torch', 'cv2', 'sklearn') if m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"
