"""The table of bad inputs of `test_bad_input.py`: every subcommand and config kind.

Each :class:`Bad` is one command line (``{d}`` stands for the test's world folder, a copy
of ``examples/``, ``fits/`` and ``data_synthetic/`` with tiny configs beside them) and a
pattern the one error line must match (it names the option, key or file at fault).
Config cases are copies of a bundled config with one line changed.
"""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path

#: The CLI options and config keys every case is run against.
SUBCOMMANDS = (
    "psf", "render", "scene", "synth", "fit", "sample", "regress", "bench", "gallery",
    "export-kernel",
)  # fmt: skip


@dataclasses.dataclass(frozen=True)
class Bad:
    """One bad input: `argv` (``{d}``: the world folder), the pattern of its error line,
    files to write first (``{name: text or bytes}``, relative to the world), and whether it
    runs in a subprocess (memory and permission cases)."""

    id: str
    argv: tuple[str, ...]
    match: str
    files: tuple[tuple[str, str | bytes], ...] = ()
    sub: bool = False

    def args(self, world: Path) -> list[str]:
        return [a.replace("{d}", str(world)) for a in self.argv]


CASES: list[Bad] = []


def bad(id: str, argv: str | list[str], match: str, files=None, sub: bool = False) -> None:
    parts = argv.split() if isinstance(argv, str) else argv
    CASES.append(Bad(id, tuple(parts), match, tuple((files or {}).items()), sub))


def edit_toml(text: str, section: str, key: str, value: str) -> str:
    """`text` with `key = value` in the table `[section]` (`""`: the top level), replacing
    the key's line there or adding it after the header."""
    lines = text.splitlines()
    header = re.compile(r"^\s*\[\[?\s*([^\]]+?)\s*\]\]?\s*(#.*)?$")
    current, start = "", 0 if section == "" else None
    for i, line in enumerate(lines):
        m = header.match(line)
        if m:
            if current == section and start is not None:
                break
            current = m.group(1)
            if current == section and start is None:
                start = i + 1
            continue
        if current == section and re.match(rf"^\s*{re.escape(key)}\s*=", line):
            lines[i] = f"{key} = {value}"
            return "\n".join(lines) + "\n"
    if start is None:
        lines += ["", f"[{section}]"]
        start = len(lines)
    lines.insert(start, f"{key} = {value}")
    return "\n".join(lines) + "\n"


# --------------------------------------------------------------------------------------
# the world's tiny configs (written by the test's fixture)

TINY_MODEL = """
[model]
kind = "aperture"
focal_length_mm = 17.0
aperture_npix = 32
window_mm = 5.0

[[model.shapes]]
kind = "disk"
diameter_mm = 4.0

[output]
npix = 32
pixel_scale_deg = 0.004

[spectrum]
wavelengths_nm = 550
"""

TINY_SPEC = """
[synth]
model = "tiny.toml"
seed = 5
out = "photo"
pixel_type = "float"

[observation]
flux = 1e6
background = 20.0
gain = 2.0
read_noise = 3.0
saturation = 60000.0
"""

TINY_FIT = """
[target]
file = "photo.exr"
saturation = 60000.0

[model]
config = "tiny.toml"

[observation]
gain = 2.0
read_noise = 3.0

[[free]]
path = "model.aperture.shapes[0].diameter_mm"
lower = 2.0
upper = 5.0

[[free]]
path = "obs.flux"
lower = 0.0
upper = inf

[solver]
n_starts = 1
max_steps = 20
"""

#: Files every world holds besides the copies of the bundled configs.
WORLD_FILES = {
    "tiny.toml": TINY_MODEL,
    "spec.toml": TINY_SPEC,
    "fit.toml": TINY_FIT,
    "latin1.toml": "[model]\nkind = 'aperture' # caf\xe9\n".encode("latin-1"),
    "utf16.toml": TINY_MODEL.encode("utf-16"),
    "binary.toml": bytes(range(256)) * 4,
    "empty.toml": "",
    "blank.toml": "\n  \n# only a comment\n",
    "nul.toml": b"[model]\x00kind = 1\n",
    "blocker": "a regular file, not a folder\n",
    "notes.txt": "not an image\n",
    "fake.exr": "not an EXR file\n",
}

# --------------------------------------------------------------------------------------
# the cases

OUT = "{d}/out"
TINY = "{d}/tiny.toml"
SCENE = "{d}/scene.exr"
FIT = "{d}/fit.toml"
SPEC = "{d}/spec.toml"
KERNEL = f"export-kernel {TINY} --for blender"
EYE = "{d}/examples/eye_daylight.toml"

# ---- config files as such: every command that reads one
for cmd, tail in (
    ("psf", f"--out {OUT}/p.exr"),
    ("synth", f"--out-dir {OUT}"),
    ("fit", f"--out-dir {OUT}/f --no-progress"),
    ("sample", f"--out-dir {OUT}/s --no-progress"),
    ("export-kernel", f"--for blender --out {OUT}/k.exr"),
):
    for name, match in (
        ("latin1", "not UTF-8 text"),
        ("utf16", "not UTF-8 text"),
        ("binary", "not UTF-8 text"),
        ("nul", "not valid TOML|NUL|null"),
        ("empty", "is empty"),
        ("blank", "is empty|no \\[|needs|no model"),
    ):
        bad(f"{cmd}-config-{name}", f"{cmd} {{d}}/{name}.toml {tail}", match)
    bad(f"{cmd}-config-folder", f"{cmd} {{d}}/examples {tail}", "is a folder")
    bad(f"{cmd}-config-device", f"{cmd} /dev/zero {tail}", "not a regular file")
    bad(f"{cmd}-config-huge", f"{cmd} {{d}}/huge.toml {tail}", "MiB")
    bad(f"{cmd}-config-missing", f"{cmd} {{d}}/nope.toml {tail}", "does not exist")
bad("render-model-latin1", f"render {SCENE} --model {{d}}/latin1.toml --out {OUT}/r.png",
    "not UTF-8 text")  # fmt: skip
bad("render-model-folder", f"render {SCENE} --model {{d}} --out {OUT}/r.png", "is a folder")
bad("render-model-empty", f"render {SCENE} --model {{d}}/empty.toml --out {OUT}/r.png",
    "is empty")  # fmt: skip
bad("gallery-model-latin1", f"gallery {{d}}/latin1.toml --out-dir {OUT}/g", "not UTF-8 text")
bad("gallery-model-missing", f"gallery {{d}}/nope.toml --out-dir {OUT}/g", "does not exist")

# ---- output paths: extension, folder, file in the way, parent a file, read-only folder
for cmd, opt, ok_ext, lead in (
    ("psf", "--out", ".exr", f"psf {TINY}"),
    ("psf-png", "--png", ".png", f"psf {TINY} --out {OUT}/ok.exr"),
    ("render", "--out", ".png", f"render {SCENE} --model {TINY}"),
    ("scene", "--out", ".exr", "scene candle --npix 32"),
    ("export-kernel", "--out", ".exr", KERNEL),
):
    bad(f"{cmd}-out-txt", f"{lead} {opt} {OUT}/x.txt", f"{opt}.*\\.txt.*{re.escape(ok_ext)}")
    bad(f"{cmd}-out-noext", f"{lead} {opt} {OUT}/x", f"{opt}.*{re.escape(ok_ext)}")
    bad(f"{cmd}-out-folder", f"{lead} {opt} {{d}}/examples", f"{opt}.*folder")
    bad(f"{cmd}-out-under-file", f"{lead} {opt} {{d}}/blocker/x{ok_ext}", f"{opt}.*not a folder")
    bad(f"{cmd}-out-readonly", f"{lead} {opt} {{d}}/readonly/x{ok_ext}", f"{opt}.*writ")
    bad(f"{cmd}-out-deep-readonly", f"{lead} {opt} {{d}}/readonly/a/b/x{ok_ext}", f"{opt}.*writ")
bad("psf-png-jpg", f"psf {TINY} --out {OUT}/ok.exr --png {OUT}/x.jpg", "--png.*\\.jpg.*\\.png")
bad("scene-out-png", f"scene candle --out {OUT}/x.png", "--out.*\\.png.*\\.exr")
bad("render-out-mp4-still", f"render {SCENE} --model {TINY} --out {OUT}/x.mp4", "--out.*\\.mp4")
bad("render-frames-out-png", f"render {SCENE} --model {TINY} --frames 2 --out {OUT}/x.png",
    "--out.*\\.png")  # fmt: skip
bad("render-frames-out-file", f"render {SCENE} --model {TINY} --frames 2 --out {{d}}/blocker",
    "--out")  # fmt: skip
for cmd, lead in (
    ("synth", f"synth {SPEC}"),
    ("fit", f"fit {FIT} --no-progress"),
    ("sample", f"sample {FIT} --no-progress"),
    ("regress", "regress aperture_fft_mono"),
    ("gallery", f"gallery {EYE} --npix 32"),
    ("bench", "bench psf --sizes 16 --repeats 1"),
):
    bad(f"{cmd}-out-dir-file", f"{lead} --out-dir {{d}}/blocker", "--out-dir.*not a folder")
    bad(f"{cmd}-out-dir-under-file", f"{lead} --out-dir {{d}}/blocker/x", "--out-dir.*not a folder")
    bad(f"{cmd}-out-dir-readonly", f"{lead} --out-dir {{d}}/readonly/x", "--out-dir.*writ")
bad("fit-out-dir-readonly-itself", f"fit {FIT} --no-progress --out-dir {{d}}/readonly",
    "--out-dir.*writ")  # fmt: skip
bad("sample-chain-is-folder", f"sample {FIT} --no-progress --out-dir {{d}}/chaindir",
    "chain.h5.*folder")  # fmt: skip
bad("regress-golden-dir-file", "regress aperture_fft_mono --golden-dir {d}/blocker", "--golden-dir")

# ---- psf options
for opt, value, match in (
    ("--npix", "0", "--npix"),
    ("--npix", "-3", "--npix"),
    ("--npix", "abc", "--npix|not a valid integer"),
    ("--pixel-scale-deg", "0", "--pixel-scale-deg"),
    ("--pixel-scale-deg", "-0.001", "--pixel-scale-deg"),
    ("--pixel-scale-deg", "nan", "--pixel-scale-deg"),
    ("--pixel-scale-deg", "inf", "--pixel-scale-deg"),
    ("--wavelengths-nm", "0", "--wavelengths-nm.*0"),
    ("--wavelengths-nm", "-550", "--wavelengths-nm.*-550"),
    ("--wavelengths-nm", "5.5e-7", "metres"),
    ("--wavelengths-nm", "nan", "--wavelengths-nm"),
    ("--wavelengths-nm", "inf", "--wavelengths-nm"),
    ("--wavelengths-nm", "abc", "--wavelengths-nm"),
    ("--wavelengths-nm", "", "--wavelengths-nm"),
    ("--wavelengths-nm", "770:380:8", "--wavelengths-nm"),
    ("--wavelengths-nm", "380:770:0", "--wavelengths-nm"),
    ("--wavelengths-nm", "380:770:-4", "--wavelengths-nm"),
    ("--wavelengths-nm", "380:770:2.5", "--wavelengths-nm"),
    ("--wavelengths-nm", "450,,650", "--wavelengths-nm"),
    ("--wavelengths-nm", "1e6", "--wavelengths-nm"),
):
    slug = re.sub(r"[^a-z0-9]+", "_", value.lower()).strip("_") or "empty"
    bad(f"psf{opt[1:]}-{slug}", ["psf", TINY, opt, value, "--out", f"{OUT}/p.exr"], match)

# ---- sizes that would exhaust memory: refused with the estimate and the limit
MEMORY = r"needs about [\d.,]+ [GM]i?B.*(limit|memory_budget_mb)"
bad("psf-npix-65536-native", f"psf {TINY} --npix 65536 --out {OUT}/p.exr", MEMORY, sub=True)
bad("psf-npix-65536-scale", f"psf {TINY} --npix 65536 --pixel-scale-deg 0.000003 --out {OUT}/p.exr",
    MEMORY, sub=True)  # fmt: skip
bad("psf-wavelengths-100000", f"psf {TINY} --wavelengths-nm 380:770:100000 --out {OUT}/p.exr",
    MEMORY, sub=True)  # fmt: skip
bad("scene-npix-65536", f"scene candle --npix 65536 --out {OUT}/s.exr", MEMORY, sub=True)
bad("export-kernel-npix-65537", f"{KERNEL} --npix 65537 --out {OUT}/k.exr", MEMORY, sub=True)
bad("gallery-npix-65536", f"gallery {EYE} --npix 65536 --out-dir {OUT}/g", MEMORY, sub=True)
bad("render-frames-huge", f"render {SCENE} --model {{d}}/examples/temporal_eye.toml "
    f"--frames 100000000 --out {OUT}/frames", MEMORY + "|--frames", sub=True)  # fmt: skip
bad("bench-sizes-huge", "bench psf --sizes 65536 --repeats 1 --out-dir {d}/out/b", MEMORY, sub=True)
bad("fit-n-starts-huge", f"fit {FIT} --n-starts 100000000 --no-progress --out-dir {OUT}/f",
    MEMORY + "|--n-starts", sub=True)  # fmt: skip
bad("sample-walkers-huge", f"sample {FIT} --walkers 100000000 --no-progress --out-dir {OUT}/s",
    MEMORY + "|--walkers", sub=True)  # fmt: skip
bad("sample-steps-huge", f"sample {FIT} --steps 10000000000000 --no-progress --out-dir {OUT}/s",
    MEMORY + "|--steps", sub=True)  # fmt: skip

# ---- render options
RENDER = f"render {SCENE} --model {TINY} --out {OUT}/r.exr"
for opt, value, match in (
    ("--mode", "blur", "--mode"),
    ("--threshold", "nan", "--threshold"),
    ("--threshold", "-1", "--threshold"),
    ("--max-bright", "0", "--max-bright"),
    ("--max-bright", "-5", "--max-bright"),
    ("--tonemap", "magic", "--tonemap"),
    ("--exposure", "nan", "--exposure"),
    ("--exposure", "-1", "--exposure"),
    ("--exposure", "0", "--exposure"),
    ("--pixel-scale-deg", "0", "--pixel-scale-deg"),
    ("--pixel-scale-deg", "nan", "--pixel-scale-deg"),
    ("--frames", "0", "--frames"),
    ("--frames", "-2", "--frames"),
    ("--fps", "0", "--fps"),
    ("--fps", "nan", "--fps"),
    ("--iterations", "0", "--iterations"),
    ("--iterations", "-1", "--iterations"),
):
    slug = re.sub(r"[^a-z0-9]+", "_", value.lower()).strip("_")
    bad(f"render{opt[1:]}-{slug}", [*RENDER.split(), opt, value], match)
bad("render-tonemap-png", f"render {SCENE} --model {TINY} --out {OUT}/r.png --tonemap magic",
    "--tonemap")  # fmt: skip
bad("render-scene-missing", f"render {{d}}/nope.exr --model {TINY} --out {OUT}/r.exr",
    "nope.exr.*(not found|does not exist)")  # fmt: skip
bad("render-scene-not-exr", f"render {{d}}/fake.exr --model {TINY} --out {OUT}/r.exr", "fake.exr")
bad("render-scene-txt", f"render {{d}}/notes.txt --model {TINY} --out {OUT}/r.exr", "notes.txt")
bad("render-scene-folder", f"render {{d}}/examples --model {TINY} --out {OUT}/r.exr", "examples")
bad("render-scene-nan", f"render {{d}}/nan_scene.exr --model {TINY} --out {OUT}/r.exr",
    "non-finite|NaN")  # fmt: skip
bad("render-scene-negative", f"render {{d}}/neg_scene.exr --model {TINY} --out {OUT}/r.exr",
    "negative")  # fmt: skip
bad("render-scene-no-scale", f"render {{d}}/noscale_scene.exr --model {TINY} --out {OUT}/r.exr",
    "--pixel-scale-deg")  # fmt: skip
bad("render-scene-dark", f"render {{d}}/dark_scene.exr --model {TINY} --mode billboard "
    f"--out {OUT}/r.exr", "dark|no light|zero")  # fmt: skip
bad("render-model-missing", f"render {SCENE} --model {{d}}/nope.toml --out {OUT}/r.exr",
    "does not exist")  # fmt: skip
bad("render-depth-missing", f"render {SCENE} --model {{d}}/examples/holographic_eye.toml "
    f"--depth {{d}}/nope.exr --out {OUT}/r.exr", "nope.exr")  # fmt: skip
bad("render-frames-static", f"render {SCENE} --model {TINY} --frames 2 --out {OUT}/anim.gif",
    "--frames")  # fmt: skip

# ---- scene options
for opt, value, match in (
    ("--npix", "0", "--npix"),
    ("--npix", "-8", "--npix"),
    ("--npix", "1", "--npix"),
    ("--npix", "x", "--npix|not a valid integer"),
    ("--seed", "-1", "--seed"),
):
    bad(f"scene{opt[1:]}-{value.lstrip('-')}{'-neg' if value.startswith('-') else ''}",
        ["scene", "candle", opt, value, "--out", f"{OUT}/s.exr"], match)  # fmt: skip
bad("scene-unknown", f"scene moonlight --out {OUT}/s.exr", "moonlight.*candle")

# ---- export-kernel options
for opt, value, match in (
    ("--for", "maya", "--for"),
    ("--npix", "64", "--npix.*odd"),
    ("--npix", "0", "--npix"),
    ("--npix", "-5", "--npix"),
    ("--viewport", "big", "--viewport"),
    ("--viewport", "0x0", "--viewport"),
    ("--viewport", "-10x20", "--viewport"),
    ("--pixel-scale-deg", "0", "--pixel-scale-deg"),
    ("--pixel-scale-deg", "nan", "--pixel-scale-deg"),
    ("--wavelengths-nm", "-550", "--wavelengths-nm"),
):
    slug = re.sub(r"[^a-z0-9]+", "_", value.lower()).strip("_")
    args = ["export-kernel", TINY, "--out", f"{OUT}/k.exr"]
    bad(f"export-kernel{opt[1:]}-{slug}", [*args, *(("--for", "unreal") if opt != "--for" else ()),
        opt, value], match)  # fmt: skip
bad("export-kernel-fov-nan", f"{KERNEL} --viewport 1920x1080 --fov-deg nan --out {OUT}/k.exr",
    "--fov-deg")  # fmt: skip
bad("export-kernel-fov-0", f"{KERNEL} --viewport 1920x1080 --fov-deg 0 --out {OUT}/k.exr",
    "--fov-deg")  # fmt: skip
bad("export-kernel-fov-200", f"{KERNEL} --viewport 1920x1080 --fov-deg 200 --out {OUT}/k.exr",
    "--fov-deg")  # fmt: skip

# ---- gallery options
for opt, value, match in (
    ("--npix", "0", "--npix"),
    ("--npix", "-16", "--npix"),
    ("--scene", "moonlight", "moonlight"),
    ("--scene-scale", "x", "--scene-scale"),
    ("--scene-scale", "0", "--scene-scale"),
    ("--scene-scale", "-2", "--scene-scale"),
    ("--scene-scale", "nan", "--scene-scale"),
    ("--wavelengths-nm", "-550", "--wavelengths-nm"),
):
    slug = re.sub(r"[^a-z0-9]+", "_", value.lower()).strip("_")
    bad(f"gallery{opt[1:]}-{slug}", ["gallery", EYE, "--out-dir", f"{OUT}/g", opt, value], match)

# ---- bench options
for opt, value, match in (
    ("--sizes", "a,b", "--sizes"),
    ("--sizes", "0", "--sizes"),
    ("--sizes", "-16", "--sizes"),
    ("--sizes", "17", "--sizes"),
    ("--repeats", "0", "--repeats"),
    ("--repeats", "-1", "--repeats"),
    ("--budget-s", "nan", "--budget-s"),
    ("--budget-s", "-1", "--budget-s"),
    ("--fit-npix", "0", "--fit-npix"),
    ("--fit-npix", "-64", "--fit-npix"),
):
    slug = re.sub(r"[^a-z0-9]+", "_", value.lower()).strip("_")
    bad(f"bench{opt[1:]}-{slug}", ["bench", "psf", "--out-dir", f"{OUT}/b", opt, value], match)
bad("bench-unknown-case", f"bench no_such_case --out-dir {OUT}/b", "no_such_case")

# ---- regress options
bad("regress-unknown-case", f"regress no_such_case --out-dir {OUT}/rg", "no_such_case")
bad("regress-update-no-reason", f"regress --update --out-dir {OUT}/rg", "--reason")
bad("regress-reason-no-update", f"regress --reason x --out-dir {OUT}/rg", "--update")
bad("regress-golden-missing", f"regress --golden-dir {{d}}/nope --out-dir {OUT}/rg", "nope")
for value, match in (
    ("x", "--cie"), ("25", "--cie"), ("25,9", "--cie.*pigment|0-1.2|1.2"), ("-5,0.5", "--cie"),
    ("nan,0.5", "--cie"), ("25,nan", "--cie"), ("500,0.5", "--cie"),
):  # fmt: skip
    bad(f"regress-cie-{re.sub(r'[^a-z0-9]+', '_', value)}",
        ["regress", "--cie", value, "--out-dir", f"{OUT}/rg"], match)  # fmt: skip

# ---- fit and sample options
for opt, value, match in (
    ("--n-starts", "0", "--n-starts"),
    ("--n-starts", "-2", "--n-starts"),
    ("--max-steps", "0", "--max-steps"),
    ("--max-steps", "-5", "--max-steps"),
):
    bad(f"fit{opt[1:]}-{value.lstrip('-')}", ["fit", FIT, "--no-progress", "--out-dir",
        f"{OUT}/f", opt, value], match)  # fmt: skip
for opt, value, match in (
    ("--steps", "0", "--steps"),
    ("--steps", "-10", "--steps"),
    ("--walkers", "3", "--walkers"),
    ("--walkers", "-4", "--walkers"),
    ("--walkers", "0", "--walkers"),
    ("--moves", "teleport", "--moves|teleport"),
    ("--batch-size", "x", "--batch-size"),
    ("--batch-size", "0", "--batch-size"),
    ("--batch-size", "-3", "--batch-size"),
):
    slug = re.sub(r"[^a-z0-9]+", "_", value.lower()).strip("_")
    bad(f"sample{opt[1:]}-{slug}", ["sample", FIT, "--no-progress", "--out-dir", f"{OUT}/s",
        opt, value], match)  # fmt: skip
bad("sample-resume-and-restart", f"sample {FIT} --resume --restart --no-progress "
    f"--out-dir {OUT}/s", "--resume.*--restart|--restart.*--resume")  # fmt: skip
bad("sample-resume-nothing", f"sample {FIT} --resume --no-progress --out-dir {{d}}/fitted",
    "no chain to resume")  # fmt: skip


# ---- model configs: every bundled example kind, one line changed
def model_case(id: str, example: str, section: str, key: str, value: str, match: str) -> None:
    """A copy of examples/`example` with `key = value` in `[section]`, through `invglare psf`."""
    src = f"examples/{example}"
    name = f"examples/_case_{id}.toml"
    edit = ((name, ("edit", src, section, key, value)),)
    argv = ("psf", "{d}/" + name, "--out", f"{OUT}/m.exr")
    CASES.append(Bad(f"model-{id}", argv, match, edit, sub=match.startswith(MEMORY)))


for ex, kind in (("circle.toml", "aperture"), ("eye_daylight.toml", "eye"),
                 ("camera_cross_screen.toml", "camera")):  # fmt: skip
    model_case(f"{kind}-npix-zero", ex, "model", "aperture_npix", "0", "aperture_npix")
    model_case(f"{kind}-npix-negative", ex, "model", "aperture_npix", "-64", "aperture_npix")
    model_case(f"{kind}-npix-float", ex, "model", "aperture_npix", "64.5", "aperture_npix")
    model_case(f"{kind}-npix-string", ex, "model", "aperture_npix", '"big"', "aperture_npix")
    model_case(f"{kind}-npix-huge", ex, "model", "aperture_npix", "65536", MEMORY)
    model_case(f"{kind}-focal-nan", ex, "model", "focal_length_mm", "nan", "focal_length_mm")
    model_case(f"{kind}-focal-negative", ex, "model", "focal_length_mm", "-17.0",
               "focal_length_mm")  # fmt: skip
    model_case(f"{kind}-window-zero", ex, "model", "window_mm", "0.0", "window_mm")
    model_case(f"{kind}-window-inf", ex, "model", "window_mm", "inf", "window_mm")
    model_case(f"{kind}-out-npix-zero", ex, "output", "npix", "0", "npix")
    model_case(f"{kind}-out-npix-bool", ex, "output", "npix", "true", "npix")
    model_case(f"{kind}-scale-negative", ex, "output", "pixel_scale_deg", "-0.001",
               "pixel_scale_deg")  # fmt: skip
    model_case(f"{kind}-scale-nan", ex, "output", "pixel_scale_deg", "nan", "pixel_scale_deg")
    model_case(f"{kind}-wl-zero", ex, "spectrum", "wavelengths_nm", "0", "wavelengths_nm")
    model_case(f"{kind}-wl-negative", ex, "spectrum", "wavelengths_nm", "-550", "wavelengths_nm")
    model_case(f"{kind}-wl-metres", ex, "spectrum", "wavelengths_nm", "5.5e-7", "metres")
    model_case(f"{kind}-wl-nan", ex, "spectrum", "wavelengths_nm", "nan", "wavelengths_nm")
    model_case(f"{kind}-wl-many", ex, "spectrum", "wavelengths_nm", '"380:770:100000"', MEMORY)
    model_case(f"{kind}-wl-empty", ex, "spectrum", "wavelengths_nm", "[]", "wavelengths_nm")
    model_case(f"{kind}-spectral-bad", ex, "spectrum", "spectral", '"fuzzy"', "spectral")
    model_case(f"{kind}-unknown-key", ex, "model", "focal_lenght_mm", "17.0", "focal_lenght_mm")
    model_case(f"{kind}-unknown-table", ex, "outptu", "npix", "64", "outptu")
model_case("aperture-disk-negative", "circle.toml", "model.shapes", "diameter_mm", "-4.0",
           "diameter_mm")  # fmt: skip
model_case("aperture-disk-nan", "circle.toml", "model.shapes", "diameter_mm", "nan", "diameter_mm")
model_case("aperture-shape-kind", "circle.toml", "model.shapes", "kind", '"star"', "star")
model_case("aperture-method", "circle.toml", "model", "method", '"fastest"', "method")
model_case("aperture-propagation", "circle.toml", "model", "propagation", '"magic"', "propagation")
model_case("kind-unknown", "circle.toml", "model", "kind", '"lens"', "model.kind.*lens")
model_case("kind-number", "circle.toml", "model", "kind", "3", "model.kind")
model_case("eye-pupil-negative", "eye_daylight.toml", "model.eye.pupil", "diameter_mm", "-3.0",
           "diameter_mm")  # fmt: skip
model_case("eye-lash-count-nan", "eye_daylight.toml", "model.eye.lashes_upper", "count", "nan",
           "count")  # fmt: skip
model_case("eye-lash-count-negative", "eye_daylight.toml", "model.eye.lashes_upper", "count",
           "-4", "count")  # fmt: skip
model_case("eye-lash-nmax-huge", "eye_daylight.toml", "model.eye.lashes_upper", "n_max",
           "100000000", MEMORY + "|n_max")  # fmt: skip
model_case("eye-seed-string", "eye_daylight.toml", "model.eye", "seed", '"x"', "seed")
model_case("camera-fnumber-zero", "camera_cross_screen.toml", "model.camera.diaphragm",
           "f_number", "0.0", "f_number")  # fmt: skip
model_case("veiling-npix-zero", "veiling_ghosts.toml", "output", "npix", "0", "npix")
model_case("veiling-npix-huge", "veiling_ghosts.toml", "output", "npix", "65536", MEMORY)
model_case("veiling-unknown-key", "veiling_ghosts.toml", "model", "ghost_count", "3", "ghost_count")
model_case("veiling-lens-npix-string", "veiling_cooke.toml", "output", "npix", '"wide"', "npix")
model_case("temporal-npix-huge", "temporal_eye.toml", "model", "aperture_npix", "65536", MEMORY)
model_case("temporal-fps-zero", "temporal_eye.toml", "model", "fps", "0.0", "fps")
model_case("temporal-fps-nan", "temporal_eye.toml", "model", "fps", "nan", "fps")
model_case("temporal-npix-zero", "temporal_eye.toml", "model", "aperture_npix", "0",
           "aperture_npix")  # fmt: skip
model_case("holographic-iterations-zero", "holographic_eye.toml", "model", "iterations", "0",
           "iterations")  # fmt: skip
model_case("holographic-mode", "holographic_eye.toml", "model", "mode", '"fast"', "mode")
model_case("holographic-npix-huge", "holographic_eye.toml", "output", "npix", "65536", MEMORY)
model_case("holographic-wl-negative", "holographic_eye.toml", "spectrum", "wavelengths_nm",
           "[-640.0, 550.0, 460.0]", "wavelengths_nm")  # fmt: skip


# ---- synth specs: the bundled ones, one line changed
def synth_case(id: str, spec: str, section: str, key: str, value: str, match: str) -> None:
    name = f"data_synthetic/_case_{id}.toml"
    edit = ((name, ("edit", f"data_synthetic/{spec}", section, key, value)),)
    CASES.append(Bad(f"synth-{id}", ("synth", "{d}/" + name, "--out-dir", f"{OUT}/syn"), match,
                     edit))  # fmt: skip


for spec in ("eye_daylight.toml", "veiling_cooke.toml", "camera_cross_screen.toml"):
    s = spec.split("_")[0]
    synth_case(f"{s}-flux-negative", spec, "observation", "flux", "-1e6", "flux")
    synth_case(f"{s}-flux-nan", spec, "observation", "flux", "nan", "flux")
    synth_case(f"{s}-flux-inf", spec, "observation", "flux", "inf", "flux")
    synth_case(f"{s}-background-negative", spec, "observation", "background", "-20.0",
               "background")  # fmt: skip
    synth_case(f"{s}-gain-zero", spec, "observation", "gain", "0.0", "gain")
    synth_case(f"{s}-read-noise-negative", spec, "observation", "read_noise", "-3.0", "read_noise")
    synth_case(f"{s}-seed-string", spec, "synth", "seed", '"x"', "seed")
    synth_case(f"{s}-seed-negative", spec, "synth", "seed", "-1", "seed")
    synth_case(f"{s}-pixel-type", spec, "synth", "pixel_type", '"double"', "pixel_type")
    synth_case(f"{s}-model-missing", spec, "synth", "model", '"nope.toml"', "nope.toml")
    synth_case(f"{s}-unknown-obs", spec, "observation", "fluxx", "1.0", "fluxx")
    synth_case(f"{s}-set-unknown", spec, "set", '"model.nothing"', "1.0", "model.nothing")
synth_case("eye-saturation-negative", "eye_daylight.toml", "observation", "saturation", "-1.0",
           "saturation")  # fmt: skip
synth_case("eye-out-path", "eye_daylight.toml", "synth", "out", '"../../escape"', "out")
synth_case("eye-set-nan", "eye_daylight.toml", "set", '"model.aperture.pupil.diameter_mm"',
           "nan", "diameter_mm")  # fmt: skip
synth_case("eye-set-negative", "eye_daylight.toml", "set", '"model.aperture.pupil.diameter_mm"',
           "-2.8", "diameter_mm")  # fmt: skip
synth_case("eye-ratio-zero", "eye_daylight.toml", "observation", "pixel_scale_ratio", "0.0",
           "pixel_scale_ratio")  # fmt: skip


# ---- fit configs: the bundled ones, one line changed
def fit_case(id: str, fit: str, section: str, key: str, value: str, match: str) -> None:
    name = f"fits/_case_{id}.toml"
    CASES.append(Bad(f"fit-{id}", ("fit", "{d}/" + name, "--no-progress", "--out-dir",
                                   f"{OUT}/fc"), match,
                     ((name, ("edit", f"fits/{fit}", section, key, value)),)))  # fmt: skip


for fit in ("eye_daylight.toml", "veiling_cooke.toml"):
    f = fit.split("_")[0]
    fit_case(f"{f}-target-missing", fit, "target", "file", '"nope.exr"', "nope.exr")
    fit_case(f"{f}-target-text", fit, "target", "file", '"../notes.txt"', "notes.txt")
    fit_case(f"{f}-target-fake", fit, "target", "file", '"../fake.exr"', "fake.exr")
    fit_case(f"{f}-model-missing", fit, "model", "config", '"nope.toml"', "nope.toml")
    fit_case(f"{f}-model-latin1", fit, "model", "config", '"../latin1.toml"', "not UTF-8")
    fit_case(f"{f}-gain-negative", fit, "observation", "gain", "-2.0", "gain")
    fit_case(f"{f}-read-noise-nan", fit, "observation", "read_noise", "nan", "read_noise")
    fit_case(f"{f}-free-path", fit, "free", "path", '"model.nothing"', "model.nothing")
    fit_case(f"{f}-free-lower-nan", fit, "free", "lower", "nan", "lower")
    fit_case(f"{f}-free-bounds-swapped", fit, "free", "upper", "-100.0", "upper|lower|bound")
    fit_case(f"{f}-free-init-outside", fit, "free", "init", "1000.0", "init")
    fit_case(f"{f}-solver-starts-zero", fit, "solver", "n_starts", "0", "n_starts")
    fit_case(f"{f}-solver-steps-negative", fit, "solver", "max_steps", "-1", "max_steps")
    fit_case(f"{f}-solver-unknown", fit, "solver", "tolerance", "1e-6", "tolerance")
    fit_case(f"{f}-views-unknown", fit, "views", "sharpness", "1.0", "sharpness")
    fit_case(f"{f}-views-negative", fit, "views", "pixels", "-1.0", "pixels")
    fit_case(f"{f}-unknown-table", fit, "fitt", "x", "1", "fitt")
fit_case("eye-saturation-negative", "eye_daylight.toml", "target", "saturation", "-5.0",
         "saturation")  # fmt: skip
# A fit's background may be negative (a dark-subtracted photo); its source's flux may not.
fit_case("veiling-flux-negative", "veiling_cooke.toml", "observation", "flux", "-1e12", "flux")
CASES.append(Bad("fit-sample-walkers", ("sample", "{d}/fits/_case_walkers.toml", "--no-progress",
                  "--out-dir", f"{OUT}/sw"), "walkers", (("fits/_case_walkers.toml", ("edit",
                  "fits/eye_daylight.toml", "sample", "walkers", "3")),)))  # fmt: skip
CASES.append(Bad("fit-config-out-dir-file", ("fit", "{d}/fits/_case_outdir.toml", "--no-progress"),
                 "out_dir.*not a folder", (("fits/_case_outdir.toml", ("edit",
                 "fits/eye_daylight.toml", "fit", "out_dir", '"../blocker/x"')),)))  # fmt: skip
