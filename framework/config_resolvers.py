"""OmegaConf resolvers our configs use; registered when `framework` is imported (Hydra imports it to compose).

`${scaled:VALUE,NUM,DEN}` is VALUE * NUM / DEN, an int when VALUE is an int (rounded). The studio's realistic preset
scales pixel widths with the resolution this way, and the trade-off points scale the profile's sizes.

`${steps:FRACTION,TOTAL}` is the step at FRACTION of a run of TOTAL steps: the training schedule's one resolver. A
profile declares every milestone (stage switch, densification window and interval, opacity resets, SH band increase,
validation) as a fraction of its `max_steps` in its `schedule:` block (conf/profile/*.yaml), and paper_full turns
them into steps with this resolver, so `profile.max_steps=N` alone moves all of them together. FRACTION may be a
number (0.25) or a ratio string ("5000/30000", the paper's own numbers); it is computed exactly (no float drift).

`${run_dir:NEW,CKPT}` is the run folder of a training command: the folder of the run whose
`<run>/checkpoints/<file>` CKPT resumes (so a resumed run continues in its own folder), else NEW.
"""

from __future__ import annotations

from fractions import Fraction
from pathlib import Path

from omegaconf import OmegaConf


def scaled(value: int | float, numerator: int | float, denominator: int | float) -> int | float:
    if float(denominator) == 0.0:
        raise ValueError(f"${{scaled:{value},{numerator},{denominator}}}: the denominator must not be 0.")
    out = float(value) * float(numerator) / float(denominator)
    return int(round(out)) if isinstance(value, int) else out


def fraction(value: int | float | str) -> Fraction:
    """A schedule fraction in [0, 1] from 0.25, 1 or "5000/30000" (exact: the float's shortest decimal form)."""
    try:
        out = Fraction(str(value).strip())
    except (ValueError, ZeroDivisionError):
        raise ValueError(
            f"schedule fraction '{value}': expected a number in [0, 1] or a ratio such as 1000/30000."
        ) from None
    if not 0 <= out <= 1:
        raise ValueError(f"schedule fraction '{value}' = {float(out):g}: expected a fraction of the run in [0, 1].")
    return out


def steps(value: int | float | str, total: int | float) -> int:
    """round(FRACTION * TOTAL) (halves up), and at least 1 for a fraction above 0, so an interval never becomes 0 and
    a milestone set after the start stays after it."""
    if int(total) != total or total < 0:
        raise ValueError(f"${{steps:{value},{total}}}: the run length must be a whole number of steps >= 0.")
    f = fraction(value)
    out = int(f * int(total) + Fraction(1, 2))  # floor(x + 1/2): halves round up, the same on every platform
    return max(out, 1) if f > 0 and total > 0 else out


def run_dir(new: str, ckpt: str | None = None, older_name: str | None = None) -> str:
    """The resumed run's folder when CKPT (or its older name, ckpt_path) is a run's checkpoint file, else NEW."""
    ckpt = ckpt or older_name
    if ckpt:
        path = Path(str(ckpt)).expanduser()
        if path.is_file() and path.parent.name == "checkpoints":
            return str(path.resolve().parent.parent)
    return new


def register() -> None:
    """Idempotent: safe to call from every entry point and test."""
    for name, fn in (("scaled", scaled), ("steps", steps), ("run_dir", run_dir)):
        if not OmegaConf.has_resolver(name):
            OmegaConf.register_new_resolver(name, fn)


register()
