"""One line of what `hydrolens analyze --json` found, for bench/peers.sh's table: the named effects with their fitted
parameters (catalogue names, CONTRACT.md), the refitted J and B, the ambiguities, and the validation NRMSE before and
after (speed / ΔP).

usage: analysis_summary.py analysis.json
"""

import json
import sys


def main():
    with open(sys.argv[1]) as f:
        d = json.load(f)
    named = [
        f["effect"] + " (" + ", ".join(f"{k} {v:.4g}" for k, v in f["parameters"].items()) + ")"
        for f in d.get("findings", [])
    ]
    p = d["improved"]["parameters"]
    parts = ["named " + ", ".join(named) if named else "no findings"]
    parts.append(f"J {p['inertia_kg_m2']:.4g}, B {p['viscous_nm_s_rad']:.4g}")
    amb = d.get("ambiguities", [])
    if amb:
        parts.append("ambiguous: " + ", ".join(" / ".join(a["effects"]) for a in amb))
    before, after = d["baseline"]["validation"], d["improved"]["validation"]

    def errors(e):
        dp = e.get("dp_nrmse")
        return f"{e['omega_nrmse']:.3f} / " + (f"{dp:.3f}" if dp is not None else "n/a")

    parts.append(f"validation NRMSE ω / ΔP {errors(before)} → {errors(after)}")
    print("; ".join(parts))


if __name__ == "__main__":
    main()
