"""Tables of docs/results_network.md, "R where the reflection is >= 20 % of the light", from a by_regime.json.

    python docs/r_share_table.py OUT/by_regime.json

(OUT from ``polspike evaluate out/datasets/stress --by-regime ... --out OUT``, the command in that section.)
Prints the per-regime table (whole-frame R / R over the rho >= 0.2 pixels, the fraction of such pixels and
the R bound of the least-squares estimate with the true zeta) and the per-group table.
"""

from __future__ import annotations

import json
import sys

COLS = ("rwps@gt", "rwps+mean@gt", "rwps@self", "net", "net@self", "net@self+mean")


def _f(v, nd=2) -> str:
    return "n/a" if v is None else f"{v:.{nd}f}"


def main(path: str) -> None:
    b = json.load(open(path))
    cols = [c for c in COLS if c in b["columns"]]
    whole = {r["regime"]: r for r in b["rows_R"]}
    print("| regime | groups | rho>=0.2 frac | R bound (LS, true zeta), dB | groups with bound >= 22 dB | rho>=0.2 px with bound >= 22 dB | flat R (oracle level) | " + " | ".join(f"{c} R: whole / rho>=0.2" for c in cols) + " |")
    print("|---|---:|---:|---:|---:|---:|---:|" + "---:|" * len(cols))
    for r in b["rows_R_share"]:
        w = whole[r["regime"]]
        nb = f"{r['n_bound_ge_22']}/{r['n_bound']}" if r.get("n_bound") else "n/a"
        print(f"| {r['regime']} | {r['n_groups']} | {_f(r['share_frac'], 3)} | {_f(r['psnr_R_bound'])} | {nb} | {_f(r.get('bound_frac_22'), 3)} | {_f(r.get('psnr_R_flat'))} | " + " | ".join(f"{_f(w.get(c))} / {_f(r.get(c))}" for c in cols) + " |")
    print()
    print("| group | rho>=0.2 frac | R bound, dB (rho>=0.2 / whole) | px with bound >= 22 dB | flat R | " + " | ".join(f"{c} R: whole / rho>=0.2" for c in cols) + " |")
    print("|---|---:|---:|---:|---:|" + "---:|" * len(cols))
    for g, s in b["groups_share"].items():
        w, m = b["groups_R"][g], b["groups_R_share"][g]
        print(f"| {g} | {_f(s['share_frac'], 3)} | {_f(s['psnr_R_bound'], 1)} / {_f(s['psnr_R_bound_all'], 1)} | {_f(s.get('bound_frac_22'), 3)} | {_f(s.get('psnr_R_flat'))} | " + " | ".join(f"{_f(w[c][0])} / {_f(m[c][0])}" for c in cols) + " |")


if __name__ == "__main__":
    main(sys.argv[1])
