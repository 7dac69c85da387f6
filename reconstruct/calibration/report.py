"""The calibration report: a text summary and plots (Malus fits, flat-field maps, PSF residual curves)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from capssim.camera.rig import RigFile  # noqa: E402
from capssim.conventions import POLARIZER_ANGLES_DEG  # noqa: E402
from capssim.files.imageio import atomic_write_bytes, atomic_write_text  # noqa: E402


def summary_lines(result: RigFile) -> list[str]:
    """One line per aperture: angle, extinction per colour, gain, corner vignetting, PSF, with uncertainties."""
    rig, unc = result.rig, result.uncertainty
    lines = [f"calibrated: {', '.join(result.calibrated) or 'nothing'}"]
    flat = rig.flat_field((64, 64)) / rig.gain[:, None, None]
    for n, nominal in enumerate(POLARIZER_ANGLES_DEG):
        parts = [f"aperture {n} ({nominal:>3} deg):"]
        if "angle_offsets_deg" in result.calibrated:
            parts.append(f"angle {nominal + rig.angle_offsets_deg[n]:.3f} +- {unc['angle_offsets_deg'][n]:.3f} deg")
            parts.append("ER " + "/".join(f"{v:.0f}" for v in rig.extinction_ratio[n]))
        if "gain" in result.calibrated:
            parts.append(f"gain {rig.gain[n]:.4f} +- {unc['gain'][n]:.4f}, corner {flat[n, 0, 0]:.3f}")
        if "psf" in result.calibrated:
            parts.append(f"PSF sigma {rig.psf[n]['sigma_hr_px']:.3f} +- {unc['psf_sigma_hr_px'][n]:.3f} HR px")
        lines.append("  ".join(parts))
    return lines


def _save(fig, path: Path) -> None:
    import io

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110, bbox_inches="tight")
    plt.close(fig)
    atomic_write_bytes(path, buf.getvalue())


def _malus_plot(result: RigFile, path: Path) -> None:
    m = result.residuals["malus"]
    phi, means, used = np.asarray(m["phi_deg"]), np.asarray(m["means"]), np.asarray(m["used"], dtype=bool)
    grid = np.linspace(0, 180, 361)
    fig, axes = plt.subplots(1, 4, figsize=(16, 3.4), sharey=True)
    for n, ax in enumerate(axes):
        for k, colour in enumerate("rgb"):
            theta = m["theta_deg_per_colour"][n][k]
            er = result.rig.extinction_ratio[n, k]
            rho = (er - 1) / (er + 1)
            ax.plot(grid, 1 + rho * np.cos(2 * np.radians(grid - theta)), color=colour, lw=1)
            ax.plot(phi[used[n, k]], means[n, k, used[n, k]], "o", color=colour, ms=3)
            ax.plot(phi[~used[n, k]], means[n, k, ~used[n, k]], "x", color=colour, ms=4)
        ax.set_title(f"aperture {n}: {POLARIZER_ANGLES_DEG[n] + result.rig.angle_offsets_deg[n]:.2f} deg")
        ax.set_xlabel("sweep polarizer angle (deg)")
    axes[0].set_ylabel("flat-corrected mean / level")
    fig.suptitle("Malus fits per aperture and colour (o used, x too close to 0 for the noise)")
    _save(fig, path)


def _flat_plot(result: RigFile, path: Path, raw_shape=(128, 128)) -> None:
    maps = result.rig.flat_field(raw_shape)
    fig, axes = plt.subplots(1, 4, figsize=(16, 3.6))
    for n, ax in enumerate(axes):
        im = ax.imshow(maps[n], vmin=maps.min(), vmax=maps.max(), cmap="gray")
        ax.set_title(f"aperture {n}: gain {result.rig.gain[n]:.4f}")
        ax.axis("off")
    fig.colorbar(im, ax=axes, shrink=0.8, label="flat field (gain x vignetting)")
    _save(fig, path)


def _psf_plot(result: RigFile, path: Path) -> None:
    p = result.residuals["psf"]
    fig, ax = plt.subplots(figsize=(6, 3.6))
    coarse = np.asarray(p["coarse_rms"])
    for n in range(4):
        ax.plot(p["coarse_sigma"], coarse[n], label=f"aperture {n}: {result.rig.psf[n]['sigma_hr_px']:.3f} HR px")
    ax.set_xlabel("Gaussian PSF sigma (HR px)")
    ax.set_ylabel("star residual RMS")
    ax.legend()
    _save(fig, path)


def write_report(result: RigFile, folder) -> Path:
    """Write ``summary.md`` and the plots of what was calibrated into ``folder``; returns ``summary.md``."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    lines = ["# Calibration report", "", f"File: `{result.path}`", "", "```", *summary_lines(result), "```", ""]
    if "malus" in result.residuals:
        _malus_plot(result, folder / "malus.png")
        lines.append("![Malus fits](malus.png)")
    if "gain" in result.calibrated:
        _flat_plot(result, folder / "flat-field.png")
        lines.append("![flat field](flat-field.png)")
    if "psf" in result.residuals:
        _psf_plot(result, folder / "psf.png")
        lines.append("![PSF fit](psf.png)")
    path = folder / "summary.md"
    atomic_write_text(path, "\n".join(lines) + "\n")
    return path


__all__ = ["summary_lines", "write_report"]

