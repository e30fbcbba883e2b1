"""Fig. 5 of the paper: a tilted mirror on the dome, its specular peak located from 20 samples under
an extended light (FRI) against 20 samples under a point light (peak picking).

Reproduces the device experiment of "Accurate recovery of a specularity from a few samples of the
reflectance function" (ICASSP 2016), Sec. 5, Fig. 5, on the emulated dome: a near-mirror whose
normal leans ``tilt`` towards the azimuth of a line of 100 light positions (signed theta), so its
peak sits at theta = 2 tilt; the 100 frames are taken once with a point light and once with an
extended one (a disk-like angular super-Gaussian, the development captures' light) at the same
positions. Every 5th frame (each of the 5 offsets) leaves 20 samples, 2 degrees apart, against a
point-light peak ~0.4 degrees wide: the point samples bracket the peak at best, while the
extended light blurs it over several samples and FRI (``torchspec.start.fri.locate``) locates the
blurred peak's centre. Errors (degrees) against the truth over tilts, offsets, noise seeds and
pixels, for: FRI on the 20 extended samples; the best point-sample methods on the 20 point
samples (argmax with parabolic, or Gaussian i.e. log-parabolic, interpolation); and, for
reference, FRI on the point samples and the 100-frame point-light peak.

The frames come from :func:`frames`: the dome (``torchspec.dome.acquire`` with the emulator, the
client and a simulated camera) when ``source`` is ``dome`` (or ``auto`` and the package has it),
else direct simulation (``torchspec.render`` and the sensor model of ``torchspec.simulate.synth``). The 100
extended frames are also a calibration capture: panel D calibrates the light from them
(``torchspec.calibration.kernel``) against the true kernel.

Panels (fig5.png): A the 100-frame responses (point and extended, one tilt) with the 20 samples
of one offset marked and the estimates; B the error distributions per method; C RMS error per
tilt; D the calibrated kernel's profile against the truth.

    python experiments/fig5_mirror.py [--config experiments/configs/fig5.yaml] [--output experiments/results]

Writes <output>/fig5/<config stem>.json and .png.
"""

from __future__ import annotations

import functools
import math
import tempfile
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import torch  # noqa: E402
from _common import parse_args  # noqa: E402

import torchspec as ts  # noqa: E402
from torchspec.atomic import save_figure, write_json  # noqa: E402
from torchspec.calibration.kernel import recover_kernel  # noqa: E402
from torchspec.config import load_config  # noqa: E402
from torchspec.model.geometry import reflect  # noqa: E402
from torchspec.model.lights import Kernel, Lights  # noqa: E402
from torchspec.model.rendering import render  # noqa: E402
from torchspec.simulate import LayoutConfig, LightConfig, layout  # noqa: E402
from torchspec.simulate.synth import MirrorConfig, SensorConfig, mirror, sense  # noqa: E402

F64 = torch.float64
SOURCES = ("auto", "simulate", "dome")
DOME_SPEED_DEG = 10_000.0  # the emulated dome's angular speed (deg/s): motions of a fraction of a millisecond


@dataclass(frozen=True)
class Calibration:
    """Settings of :func:`torchspec.calibration.kernel.recover_kernel` for panel D."""

    size: int = 32
    mirror_alpha: float = 0.0
    smoothing: float = 0.03


@dataclass(frozen=True)
class Extended:
    """An extended light (the keys of :class:`torchspec.simulate.LightConfig`) and its label."""

    label: str
    kernel: str
    domain: str = "angular"
    sigma: float = 0.03
    power: float = 2.0

    def config(self) -> LightConfig:
        return LightConfig(kernel=self.kernel, domain=self.domain, sigma=self.sigma, power=self.power)


@dataclass(frozen=True)
class Settings:
    mirror: MirrorConfig  # its tilt_deg is replaced by each of tilts_deg; width x height pixels = noise draws
    tilts_deg: tuple[float, ...]
    azimuth_deg: float  # of the line of lights and of the mirror's lean
    frames: int
    theta_min_deg: float
    theta_max_deg: float
    lights: tuple[Extended, ...]  # the extended lights, each against the same point light
    step: int  # every step-th frame; each offset 0..step-1 is a trial
    sensor: SensorConfig  # its seed is replaced by each of range(seeds)
    seeds: int
    fri_method: str = "coherent"
    fri_coefficients: int | None = None  # M; None: every bin below Nyquist
    fri_sweep: tuple[int, ...] = ()  # other M to report (RMS only)
    source: str = "auto"
    calibration: Calibration = field(default_factory=Calibration)


COLOURS = ("tab:orange", "tab:green", "tab:red", "tab:purple")


def _maps(settings: Settings, tilt_deg: float):
    """The mirror, leaning ``tilt_deg`` towards the line's azimuth."""
    return mirror(replace(settings.mirror, tilt_deg=tilt_deg, tilt_azimuth_deg=settings.azimuth_deg), dtype=F64)[0]


def _view() -> torch.Tensor:
    return torch.tensor([0.0, 0.0, 1.0], dtype=F64)


def _centres(settings: Settings) -> torch.Tensor:
    return layout(
        LayoutConfig(
            kind="line",
            n=settings.frames,
            azimuth_deg=settings.azimuth_deg,
            theta_min_deg=settings.theta_min_deg,
            theta_max_deg=settings.theta_max_deg,
        )
    )


def _kernel(light: LightConfig) -> Kernel:
    if light.kernel == "point":
        return Kernel("point")
    return Kernel(light.kernel, light.domain, light.sigma, light.power)


def _dome_available() -> bool:
    try:
        from torchspec.dome import (  # noqa: F401
            DomeClient,
            DomeEmulator,
            SimulatedCamera,
            acquire,  # noqa: F401
        )
    except ImportError:
        return False
    return True


@functools.lru_cache(maxsize=64)
def _simulate(settings: Settings, tilt_deg: float, light: LightConfig) -> torch.Tensor:
    """Noise-free frames ``(P, K)`` of the mirror's pixels, rendered directly."""
    maps = _maps(settings, tilt_deg)
    centres = _centres(settings)
    count = centres.shape[0]
    lights = Lights(centres, _kernel(light), torch.ones(count, 1, dtype=F64), torch.ones(count, dtype=F64))
    return render(maps, lights, _view()).mean(-1).flatten(0, 1)  # (P, K)


def frames(settings: Settings, tilt_deg: float, light: LightConfig, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The ``K`` frames of one acquisition: the light centres ``(K, 3)`` and the recorded values
    ``(P, K)`` of the mirror's ``P`` pixels (exposure and irradiance divided out)."""
    source = settings.source
    if source == "auto":
        source = "dome" if _dome_available() else "simulate"
    if source == "dome":  # acquired once noise-free; each seed's noise as the camera's sensor draws it
        centres, clean = _acquire(settings, tilt_deg, light)
    else:
        centres, clean = _centres(settings), _simulate(settings, tilt_deg, light)
    recorded, _ = sense(clean, replace(settings.sensor, seed=seed))
    return centres, recorded / settings.sensor.exposure


@functools.lru_cache(maxsize=64)
def _acquire(settings: Settings, tilt_deg: float, light: LightConfig) -> tuple[torch.Tensor, torch.Tensor]:
    """Noise-free frames ``(P, K)`` acquired on the emulated dome: the emulator on a pseudo-terminal,
    the serial client, a simulated camera rendering the mirror, ``torchspec.dome.acquire`` writing
    the capture (an extended light recorded as ``unknown``, as before calibration), read back."""
    from torchspec.dome import DomeClient, DomeEmulator, LightSettings, SimulatedCamera, acquire
    from torchspec.io import LightSpec

    top = settings.theta_max_deg
    if settings.azimuth_deg != 0.0 or settings.theta_min_deg != -top or not 0 < top < 90:
        raise ValueError(
            "the dome's line layout runs along azimuth 0 from -theta to +theta: azimuth_deg must be 0 and "
            f"theta_min_deg = -theta_max_deg; got {settings.azimuth_deg}, {settings.theta_min_deg}, {top}. "
            "Change the config, or use source: simulate."
        )
    kernel = _kernel(light)
    recorded = LightSpec(kernel="point") if kernel.kind == "point" else LightSpec(kernel="unknown", symmetric=True)
    camera = SimulatedCamera(_maps(settings, tilt_deg), kernel, sensor=SensorConfig(exposure=1.0))
    with tempfile.TemporaryDirectory() as folder, DomeEmulator(speed=math.radians(DOME_SPEED_DEG)) as emulator:
        with DomeClient(emulator.port, timeout=2.0) as client:
            capture = acquire(
                client,
                camera,
                Path(folder) / "capture",
                light=LightSettings(recorded),
                layout=f"line:{settings.frames}",
                radius=math.sin(math.radians(top)),
                progress=False,
            )
        stack = capture.read_frames(dtype=F64)  # (K, C, H, W)
    scale = capture.exposure()[:, None] * capture.irradiance()
    values = (stack / scale[:, :, None, None]).mean(1).flatten(1).T
    centres = capture.directions()
    gap = float((centres - _centres(settings)).abs().max())
    if gap > 1e-9:  # the dome's plan must be the settings' line
        raise RuntimeError(f"the dome's light positions differ from the settings' line by {gap:.3g}.")
    return centres, values


def _truth(settings: Settings, tilt_deg: float) -> float:
    """The signed theta (deg) along the line of the direction the mirror reflects the view into."""
    r = reflect(_view(), _maps(settings, tilt_deg).normal[0, 0])
    a = math.radians(settings.azimuth_deg)
    along = float(r[0]) * math.cos(a) + float(r[1]) * math.sin(a)
    return math.degrees(math.atan2(along, float(r[2])))


def _parabola(y: torch.Tensor, theta: torch.Tensor, log: bool) -> torch.Tensor:
    """Argmax of each row of ``y (T, N)`` at uniform ``theta (T, N)``, refined by the parabola
    through it and its neighbours (of ``log y`` for a Gaussian peak)."""
    n = y.shape[-1]
    k = y.argmax(-1).clamp(1, n - 2)
    rows = torch.arange(y.shape[0])
    a, b, c = y[rows, k - 1], y[rows, k], y[rows, k + 1]
    if log:
        tiny = torch.finfo(y.dtype).tiny
        a, b, c = (torch.log(v.clamp(min=tiny)) for v in (a, b, c))
    denominator = a - 2.0 * b + c
    shift = torch.where(denominator < 0, 0.5 * (a - c) / denominator, torch.zeros_like(b)).clamp(-0.5, 0.5)
    step = theta[:, 1] - theta[:, 0]
    return theta[rows, k] + shift * step


def _fri(y: torch.Tensor, theta: torch.Tensor, method: str, coefficients: int | None) -> torch.Tensor:
    """FRI location of each row's blurred peak: samples uniform over one period from ``theta[:, 0]``."""
    n = y.shape[-1]
    step = float(theta[0, 1] - theta[0, 0])
    found = ts.start.fri.locate(y, period=n * step, method=method, num_coefficients=coefficients)
    return theta[:, 0] + found.position


def _methods(settings: Settings) -> dict[str, tuple[str, str]]:
    """Row name -> (light, how): ``light`` ``point`` or an extended light's index; ``how`` ``fri``,
    ``parabola``, ``gaussian`` (log-parabola) or ``dense`` (the parabola on every frame)."""
    n = settings.frames // settings.step
    rows = {}
    for i, light in enumerate(settings.lights):
        rows[f"{light.label}: FRI ({n})"] = (str(i), "fri")
    rows[f"point: argmax + parabola ({n})"] = ("point", "parabola")
    rows[f"point: argmax + Gaussian ({n})"] = ("point", "gaussian")
    rows[f"point: FRI ({n})"] = ("point", "fri")
    for i, light in enumerate(settings.lights):
        rows[f"{light.label}: argmax + parabola ({n})"] = (str(i), "parabola")
    rows[f"point: argmax + parabola (all {settings.frames})"] = ("point", "dense")
    return rows


def _subsample(values: torch.Tensor, theta: torch.Tensor, step: int) -> tuple[torch.Tensor, torch.Tensor]:
    """``(P * step, N)`` samples and positions: each pixel's every ``step``-th frame, per offset."""
    count = values.shape[-1] // step
    ys, ts_ = [], []
    for offset in range(step):
        index = torch.arange(offset, offset + count * step, step)
        ys.append(values[:, index])
        ts_.append(theta[index].expand(values.shape[0], -1))
    return torch.cat(ys), torch.cat(ts_)


def run(settings: Settings) -> dict:
    if settings.source not in SOURCES:
        raise ValueError(f"source must be one of {SOURCES}; got {settings.source!r}.")
    if not settings.lights:
        raise ValueError("lights must name at least one extended light.")
    source = settings.source if settings.source != "auto" else ("dome" if _dome_available() else "simulate")
    settings = replace(settings, source=source)
    theta = torch.linspace(settings.theta_min_deg, settings.theta_max_deg, settings.frames, dtype=F64)
    methods = _methods(settings)
    errors = {name: [] for name in methods}
    sweep = {
        f"{light}: FRI M={m}": []
        for light in ["point"] + [x.label for x in settings.lights]
        for m in settings.fri_sweep
    }
    per_tilt = []
    example = None
    for tilt in settings.tilts_deg:
        truth = _truth(settings, tilt)
        tilt_errors = {name: [] for name in methods}
        for seed in range(settings.seeds):
            values = {"point": frames(settings, tilt, LightConfig(kernel="point"), 10_000 + seed)[1]}
            for i, light in enumerate(settings.lights):
                values[str(i)] = frames(settings, tilt, light.config(), 1_000 * i + seed)[1]
            samples = {key: _subsample(v, theta, settings.step) for key, v in values.items()}
            for name, (light, how) in methods.items():
                if how == "dense":
                    found = _parabola(values[light], theta.expand(values[light].shape[0], -1), log=False)
                elif how == "fri":
                    found = _fri(*samples[light], settings.fri_method, settings.fri_coefficients)
                else:
                    found = _parabola(*samples[light], log=how == "gaussian")
                error = (found - truth).tolist()
                errors[name] += error
                tilt_errors[name] += error
            for m in settings.fri_sweep:
                for key, label in [("point", "point")] + [(str(i), x.label) for i, x in enumerate(settings.lights)]:
                    sweep[f"{label}: FRI M={m}"] += (_fri(*samples[key], settings.fri_method, m) - truth).tolist()
            # The example of panel A: the tilt whose peak falls farthest from the samples of offset 0.
            gap = float((theta[:: settings.step] - truth).abs().min())
            if seed == 0 and (example is None or gap > example["gap"]):
                example = {
                    "tilt": tilt,
                    "truth": truth,
                    "theta": theta,
                    "gap": gap,
                    **{k: v[0] for k, v in values.items()},
                }
        per_tilt.append(
            {
                "tilt_deg": tilt,
                "truth_deg": truth,
                "rms_deg": {name: _rms(e) for name, e in tilt_errors.items()},
            }
        )
    return {
        "settings": asdict(settings),
        "trials_per_method": len(next(iter(errors.values()))),
        "samples": settings.frames // settings.step,
        "spacing_deg": {
            "frames": float(theta[1] - theta[0]),
            "samples": settings.step * float(theta[1] - theta[0]),
        },
        "methods": {name: _stats(e) for name, e in errors.items()},
        "fri_sweep_rms_deg": {name: _rms(e) for name, e in sweep.items()},
        "per_tilt": per_tilt,
        "calibration": [_calibrate(settings, light) for light in settings.lights],
        "_example": example,
        "_errors": errors,
    }


def _rms(errors: list[float]) -> float:
    return math.sqrt(sum(e * e for e in errors) / len(errors))


def _stats(errors: list[float]) -> dict:
    e = torch.tensor(errors, dtype=F64).abs()
    return {
        "rms_deg": _rms(errors),
        "median_abs_deg": float(e.median()),
        "p95_abs_deg": float(torch.quantile(e, 0.95)),
        "max_abs_deg": float(e.max()),
        "bias_deg": float(torch.tensor(errors, dtype=F64).mean()),
    }


def _calibrate(settings: Settings, light: Extended) -> dict:
    """The light calibrated from the 100 extended frames of the first tilt (seed 0), against the truth."""
    tilt = settings.tilts_deg[0]
    centres, values = frames(settings, tilt, light.config(), 0)
    result = recover_kernel(values, centres, view=_view(), **asdict(settings.calibration))
    kernel = _kernel(light.config())
    r = reflect(_view(), _maps(settings, tilt).normal[0, 0])[:2]
    reach = result.extent
    radius = torch.linspace(0.0, reach, 200, dtype=F64)
    a = math.radians(settings.azimuth_deg)
    axis = torch.tensor([math.cos(a), math.sin(a)], dtype=F64)
    u = radius[:, None] * axis
    lk = r - u  # the frame centre that puts the reflection at offset u
    truth = kernel.density(r.expand_as(u), torch.cat([lk, torch.sqrt(1.0 - (lk * lk).sum(-1, keepdim=True))], -1))
    found = result.kernel().density(u, _view())
    return {
        "light": light.label,
        "radius": radius.tolist(),
        "true_density": truth.tolist(),
        "calibrated_density": found.tolist(),
        "profile_relative_l2": float((found - truth).norm() / truth.norm()),
        "std": result.stats["std"],
        "true_std": float(kernel.covariance(torch.cat([r, torch.sqrt(1 - r.dot(r))[None]])).diagonal().sqrt().mean()),
        "extent": result.extent,
        "summary": result.summary(),
    }


def _figure(result: dict, settings: Settings):
    fig, axes = plt.subplots(1, 4, figsize=(22, 5.6))
    ex = result["_example"]
    theta = ex["theta"].numpy()
    step = settings.step
    ax = axes[0]
    curves = [("point", "point light", "tab:blue")]
    curves += [(str(i), x.label, c) for (i, x), c in zip(enumerate(settings.lights), COLOURS, strict=False)]
    for key, label, colour in curves:
        y = ex[key].numpy()
        ax.plot(theta, y / y.max(), "-", color=colour, lw=1, label=f"{label}, {len(theta)} frames")
        ax.plot(theta[::step], y[::step] / y.max(), "o", color=colour, ms=4, label=f"{label}: the {len(theta) // step}")
    ax.axvline(ex["truth"], color="k", ls=":", lw=1, label=f"true peak {ex['truth']:.2f} deg")
    ax.set_xlim(ex["truth"] - 10, ex["truth"] + 10)
    ax.set_xlabel("light theta (deg, signed along the line)")
    ax.set_ylabel("response / its maximum")
    ax.set_title(f"A  mirror tilted {ex['tilt']:g} deg: one pixel's responses")
    ax.legend(fontsize=6, loc="upper left")
    ax = axes[1]
    names = list(result["methods"])
    data = [[max(abs(e), 1e-6) for e in result["_errors"][n]] for n in names]
    ax.boxplot(data, orientation="horizontal", whis=(5, 95), showfliers=False)
    labels = [f"{n}\nrms {result['methods'][n]['rms_deg']:.3f} deg" for n in names]
    ax.set_yticks(range(1, len(names) + 1), labels, fontsize=7)
    ax.invert_yaxis()
    ax.set_xscale("log")
    ax.set_xlabel("|location error| (deg); box: quartiles, whiskers: 5-95 %")
    ax.set_title(f"B  location error, {result['trials_per_method']} trials per row")
    ax = axes[2]
    tilts = [row["tilt_deg"] for row in result["per_tilt"]]
    for n in names:
        ax.plot(tilts, [row["rms_deg"][n] for row in result["per_tilt"]], "o-", ms=3, label=n)
    ax.set_yscale("log")
    ax.set_xlabel("mirror tilt (deg): the peak at 2 tilt moves across the samples")
    ax.set_ylabel("RMS error (deg)")
    ax.set_title("C  RMS error per tilt")
    ax.legend(fontsize=6, loc="upper center", bbox_to_anchor=(0.5, -0.16), ncol=2)
    ax = axes[3]
    for cal, colour in zip(result["calibration"], COLOURS, strict=False):
        radius = [math.degrees(r) for r in cal["radius"]]
        ax.plot(radius, cal["true_density"], "-", color=colour, lw=2.5, alpha=0.4, label=f"{cal['light']}: truth")
        ax.plot(
            radius,
            cal["calibrated_density"],
            "--",
            color=colour,
            lw=1.5,
            label=f"calibrated (rel. L2 {100 * cal['profile_relative_l2']:.1f} %)",
        )
    ax.set_xlabel("offset from the light's centre (~deg)")
    ax.set_ylabel("kernel density (per unit l-plane area)")
    ax.set_title(f"D  lights calibrated from the {settings.frames} frames")
    ax.legend(fontsize=7)
    fig.tight_layout()
    return fig


def main(argv: list[str] | None = None) -> dict:
    args = parse_args(__doc__, "fig5.yaml", argv)
    settings = load_config(args.config, Settings)
    result = run(settings)
    print(
        f"frames from: {result['settings']['source']}; {result['trials_per_method']} trials per method "
        f"({len(settings.tilts_deg)} tilts x {settings.seeds} seeds x {settings.step} offsets x pixels); "
        f"{result['samples']} samples {result['spacing_deg']['samples']:.2f} deg apart"
    )
    print(f"{'method':44s} {'rms':>8s} {'median':>8s} {'p95':>8s} {'max':>8s} {'bias':>9s}  (deg)")
    for name, row in result["methods"].items():
        print(
            f"{name:44s} {row['rms_deg']:8.4f} {row['median_abs_deg']:8.4f} {row['p95_abs_deg']:8.4f} "
            f"{row['max_abs_deg']:8.4f} {row['bias_deg']:+9.4f}"
        )
    if result["fri_sweep_rms_deg"]:
        print(
            "FRI RMS error (deg) against the number of coefficients M: "
            + ", ".join(f"{name} {rms:.4f}" for name, rms in result["fri_sweep_rms_deg"].items())
        )
    for cal in result["calibration"]:
        print(
            f"{cal['light']}: calibrated from the {settings.frames} frames, profile rel. L2 "
            f"{100 * cal['profile_relative_l2']:.2f} %, std {cal['std'][0]:.4g} (truth {cal['true_std']:.4g})"
        )
    folder = args.output / "fig5"
    stem = args.config.stem
    public = {k: v for k, v in result.items() if not k.startswith("_")}
    write_json(folder / f"{stem}.json", public)
    save_figure(_figure(result, settings), folder / f"{stem}.png")
    print(f"wrote {folder / f'{stem}.json'} and {folder / f'{stem}.png'}")
    return public


if __name__ == "__main__":
    main()
