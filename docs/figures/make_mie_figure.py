"""Figure for docs/optics.md: Mie phase functions of water clouds against Henyey-Greenstein.

Run from the repository root:  python docs/figures/make_mie_figure.py
Writes docs/figures/mie_phase_functions.png from the default Mie table (0.672 micron,
v_eff = 0.1), shipped with the package.
"""

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from cloudct.physics.mie import mie_table  # noqa: E402
from cloudct.physics.phase import henyey_greenstein_phase  # noqa: E402

OUT = Path(__file__).resolve().parent / "mie_phase_functions.png"


def main() -> None:
    table = mie_table()
    angles = table["scattering_angle"].values
    fig, (ax, inset) = plt.subplots(1, 2, figsize=(10, 4.2), width_ratios=(2, 1))
    for reff, colour in ((5.0, "tab:blue"), (10.0, "tab:orange"), (20.0, "tab:red")):
        row = table.sel(reff=reff)
        label = rf"Mie, $r_{{\rm eff}}$ = {reff:g} $\mu$m (g = {float(row['g']):.3f})"
        for axis in (ax, inset):
            axis.semilogy(angles, row["phase"].values, color=colour, lw=1.2, label=label)
    hg = [henyey_greenstein_phase(np.cos(np.radians(a)), 0.85) for a in angles]
    for axis in (ax, inset):
        axis.semilogy(angles, hg, color="k", ls="--", lw=1.2, label="Henyey-Greenstein, g = 0.85")
        axis.set_xlabel("scattering angle [deg]")
        axis.grid(True, which="major", alpha=0.3)
    ax.set_xlim(0, 180)
    ax.set_xticks(range(0, 181, 30))
    ax.set_ylabel(r"phase function [sr$^{-1}$]")
    ax.set_title(
        rf"Water droplets, $\lambda$ = {table.attrs['wavelength']} $\mu$m, "
        rf"$v_{{\rm eff}}$ = {table.attrs['veff']}"
    )
    ax.legend(fontsize=8, loc="upper right")
    inset.set_xlim(0, 10)
    inset.set_title("forward peak")
    fig.tight_layout()
    fig.savefig(OUT, dpi=130)
    plt.close(fig)
    print(f"wrote {OUT}")


if __name__ == "__main__":
    main()
