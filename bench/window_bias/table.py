#!/usr/bin/env python3
"""The report's table. Usage: table.py NUISANCE SELECT [brake-nuisance]. Per config: window-level J error % (median,
IQR over all windows of all seeds), per-recording pooled J error % (median over seeds [min,max]) for:
  wm  = mean of the windows' θ weighted by each window's own variance (F, IV: a = 1/J pooled, then J = 1/a; R: J)
  sum = sum of the windows' nuisance-partialled normal equations (RLS with λ = 1, no rejection)
and B error % of wm. Rt = reverse on the noise-free speed (sum), F_TL = forward with ∫T_L known (sum), EST = `hydrolens estimate` (rls-sgd) from a nominal J of 0.05."""
import glob, json, re, statistics as st, sys, tomllib
sys.path.insert(0, "."); from fitwin import solve, PART
nuis, sel = sys.argv[1], sys.argv[2]
bnuis = sys.argv[3] if len(sys.argv) > 3 else nuis
P = {k: i for i, k in enumerate(PART)}
def q(xs, p):
    xs = sorted(xs); k = (len(xs) - 1) * p; i = int(k); return xs[i] + (xs[min(i + 1, len(xs) - 1)] - xs[i]) * (k - i)
G = {}
for fn in sorted(glob.glob("fits/*.jsonl")):
    b, nu = re.match(r"fits/(.*)\.(poly2|step)\.jsonl", fn).groups()
    if nu != (bnuis if b.startswith("brake") else nuis): continue
    mot = tomllib.load(open(f"models/{b}.toml", "rb"))["motor"]
    J0, B0 = mot["inertia_kg_m2"], mot["viscous_nm_s_rad"]
    ws = [json.loads(l) for l in open(fn)]
    ws = [w for w in ws if "part" in w and (sel == "all" or (sel == "f" and w["f_range"] >= 2.0)
                                            or (sel == "moved" and (w["moved"] or 0) > 100))]
    M = [[sum(w["part"][i][j] for w in ws) for j in range(len(PART))] for i in range(len(PART))]
    def pool(y, xs, zs=None):
        zs = zs or xs
        return solve([[M[P[z]][P[x]] for x in xs] for z in zs], [M[P[z]][P[y]] for z in zs])
    r = {"win": {}, "wm": {}, "sum": {}}
    for me in ["F", "R", "IV"]:
        v = [w[me] for w in ws if w.get(me) and w[me][2] > 0 and w[me][3] > 0]
        r["win"][me] = [100 * (x[0] / J0 - 1) for x in v]
        if me == "R":
            J = sum(x[0] / x[2] for x in v) / sum(1 / x[2] for x in v)
        else:  # a = 1/J, var(a) = var(J)/J^4
            wa = [x[0] ** 4 / x[2] for x in v]
            J = sum(wa) / sum(w_ / x[0] for w_, x in zip(wa, v))
        Bm = sum(x[1] / x[3] for x in v) / sum(1 / x[3] for x in v)
        r["wm"][me] = (100 * (J / J0 - 1), 100 * (Bm / B0 - 1))
    a, c = pool("w", ["It", "Iw"]); r["sum"]["F"] = 100 * (1 / a / J0 - 1)
    Jr, _ = pool("It", ["w", "Iw"]); r["sum"]["R"] = 100 * (Jr / J0 - 1)
    a, c = pool("w", ["It", "Iw"], ["f", "If"]); r["sum"]["IV"] = 100 * (1 / a / J0 - 1)
    Jr, _ = pool("It", ["wt", "Iwt"]); r["sum"]["Rt"] = 100 * (Jr / J0 - 1)
    try:
        a, c, d = pool("w", ["It", "Iw", "IL"]); r["sum"]["F_TL"] = 100 * (1 / a / J0 - 1)
    except Exception: r["sum"]["F_TL"] = float("nan")
    e = open(f"est/{b}.final").read().split(","); r["sum"]["EST"] = 100 * (float(e[0]) / J0 - 1)
    G.setdefault(re.sub(r"_s\d+$", "", b), []).append(r)
def rng(vals):
    vals = [v for v in vals if v == v]
    return f"{st.median(vals):+.0f}[{min(vals):+.0f},{max(vals):+.0f}]" if vals else "-"
print(f"# nuisance {nuis} (brake: {bnuis}), windows {sel}; seeds 11-13; J true 0.08, B true 0.04")
print("| load | ms | window J F / R / IV: median (p25,p75) | wm J F / R / IV | sum J F / R / IV | Rt | F_TL | EST | wm B F / R / IV |")
for key in sorted(G, key=lambda k: (int(re.search(r'ms(\d+)', k).group(1)), k)):
    g = G[key]; name, ms = re.match(r"(.*)_ms(\d+)", key).groups()
    name = name.replace("rand_", "rand ").replace("_c", " c")
    win = " / ".join(f"{q(sum((x['win'][m] for x in g), []), .5):+.0f}({q(sum((x['win'][m] for x in g), []), .25):+.0f},{q(sum((x['win'][m] for x in g), []), .75):+.0f})" for m in ["F", "R", "IV"])
    wm = " / ".join(rng([x["wm"][m][0] for x in g]) for m in ["F", "R", "IV"])
    sm = " / ".join(rng([x["sum"][m] for x in g]) for m in ["F", "R", "IV"])
    bw = " / ".join(rng([x["wm"][m][1] for x in g]) for m in ["F", "R", "IV"])
    print(f"| {name} | {ms} | {win} | {wm} | {sm} | {rng([x['sum']['Rt'] for x in g])} | {rng([x['sum']['F_TL'] for x in g])} | {rng([x['sum']['EST'] for x in g])} | {bw} |")
