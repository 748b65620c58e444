#!/usr/bin/env python3
"""Per-window J, B fits on a hydrolens `simulate` recording: forward (as windows.rs), reverse, IV; plus diagnostics.
Plain Python (no numpy). Usage: fitwin.py rec.csv model.toml out.jsonl [--step]
Columns of the window Gram matrix (all integrals trapezoidal from the window start, like rls_sgd.rs):
  It  = ∫τ (τ = D_m Δp)   Iw = ∫ω_meas   w = ω_meas   Iwt = ∫ω_true   wt = ω_true
  f = f_drive   If = ∫f   IIf = ∫∫f   IL = ∫T_L(true)   1, u, u²  (u = s / 1.5 s)   [step: (u-u_k)+]
"""
import csv, json, math, sys, tomllib

L_S, STRIDE_S = 1.5, 0.75
NAMES = ["It", "Iw", "w", "Iwt", "wt", "f", "If", "IIf", "IL", "c1", "u", "u2"]
IX = {n: i for i, n in enumerate(NAMES)}
STEP = len(NAMES)
PART = ["It", "Iw", "w", "Iwt", "wt", "f", "If", "IIf", "IL"]  # index of the step column when present


def solve(A, b):
    """Solve A x = b (small dense), with column scaling and partial pivoting. Returns x or None."""
    n = len(A)
    d = [1.0 / math.sqrt(abs(A[i][i])) if A[i][i] != 0 else 1.0 for i in range(n)]
    M = [[A[i][j] * d[i] * d[j] for j in range(n)] + [b[i] * d[i]] for i in range(n)]
    for c in range(n):
        p = max(range(c, n), key=lambda r: abs(M[r][c]))
        if abs(M[p][c]) < 1e-13:
            return None
        M[c], M[p] = M[p], M[c]
        for r in range(c + 1, n):
            fct = M[r][c] / M[c][c]
            if fct:
                Mr, Mc = M[r], M[c]
                for k in range(c, n + 1):
                    Mr[k] -= fct * Mc[k]
    x = [0.0] * n
    for i in range(n - 1, -1, -1):
        s = M[i][n] - sum(M[i][k] * x[k] for k in range(i + 1, n))
        x[i] = s / M[i][i]
    return [x[i] * d[i] for i in range(n)]


def inverse(A):
    n = len(A)
    cols = []
    for j in range(n):
        e = [0.0] * n
        e[j] = 1.0
        x = solve(A, e)
        if x is None:
            return None
        cols.append(x)
    return [[cols[j][i] for j in range(n)] for i in range(n)]


def matmul(A, B):
    return [[sum(A[i][k] * B[k][j] for k in range(len(B))) for j in range(len(B[0]))] for i in range(len(A))]


def fit(G, y, xs, zs=None):
    """OLS (zs None) or just-identified IV of column y on columns xs (instruments zs). G: Gram matrix (incl. step).
    Returns (beta, cov, s2)."""
    n_obs = G["n"]
    g = G["g"]
    X = [[g[a][b] for b in xs] for a in xs]
    Xy = [g[a][y] for a in xs]
    if zs is None:
        beta = solve(X, Xy)
        if beta is None:
            return None
        inv = inverse(X)
        if inv is None:
            return None
    else:
        ZX = [[g[a][b] for b in xs] for a in zs]
        Zy = [g[a][y] for a in zs]
        beta = solve(ZX, Zy)
        if beta is None:
            return None
        ZXi = inverse(ZX)
        if ZXi is None:
            return None
        ZZ = [[g[a][b] for b in zs] for a in zs]
        XZi = [list(r) for r in zip(*ZXi)]
        inv = matmul(matmul(ZXi, ZZ), XZi)
    rss = g[y][y] - 2 * sum(beta[i] * Xy[i] for i in range(len(xs))) + sum(
        beta[i] * X[i][j] * beta[j] for i in range(len(xs)) for j in range(len(xs)))
    s2 = max(rss, 1e-300) / max(n_obs - len(xs), 1)
    cov = [[s2 * v for v in r] for r in inv]
    return beta, cov, s2, rss


def jb_forward(r):
    """ω = .. + a·It − c·Iw: J = 1/a, B = c/a (c enters with a minus: the column is -Iw, so beta[1] = -c)."""
    beta, cov = r[0], r[1]
    a, c = beta[0], beta[1]  # the column is -Iw, so beta[1] = c
    if a <= 0:
        return None
    J, B = 1 / a, c / a
    # delta method
    gJ = [-1 / a ** 2, 0.0]
    gB = [-c / a ** 2, 1 / a]
    vJ = sum(gJ[i] * cov[i][j] * gJ[j] for i in range(2) for j in range(2))
    vB = sum(gB[i] * cov[i][j] * gB[j] for i in range(2) for j in range(2))
    return J, B, vJ, vB


def jb_reverse(r):
    beta, cov = r[0], r[1]
    return beta[0], -beta[1], cov[0][0], cov[1][1]  # the column is -Iw


def main():
    rec, model, out = sys.argv[1], sys.argv[2], sys.argv[3]
    with_step = "--step" in sys.argv
    m = tomllib.load(open(model, "rb"))
    Dm = m["motor"]["displacement_cm3"] * 1e-6 / (2 * math.pi) * 1e5  # N·m per bar
    J0, B0 = m["motor"]["inertia_kg_m2"], m["motor"]["viscous_nm_s_rad"]
    sig_w = m["sensors"]["speed_noise_rad_s"]
    rows = list(csv.reader(open(rec)))
    h = {k: i for i, k in enumerate(rows[0])}
    data = rows[1:]
    t = [float(r[h["t_s"]]) for r in data]
    tau = [Dm * (float(r[h["p_in_bar"]]) - float(r[h["p_out_bar"]])) for r in data]
    w = [float(r[h["omega_rad_s"]]) for r in data]
    wt = [float(r[h["true_omega_rad_s"]]) for r in data]
    f = [float(r[h["f_drive_hz"]]) for r in data]
    TL = [float(r[h["true_load_nm"]]) for r in data]
    dt = t[1] - t[0]
    n = int(round(L_S / dt)) + 1
    stride = int(round(STRIDE_S / dt))
    fo = open(out, "w")
    for s0 in range(0, len(t) - n + 1, stride):
        idx = range(s0, s0 + n)
        # integrals
        It = Iw = Iwt = If = IIf = IL = 0.0
        cols = []
        prev = None
        for i in idx:
            if prev is not None:
                It += dt * 0.5 * (tau[prev] + tau[i])
                Iw += dt * 0.5 * (w[prev] + w[i])
                Iwt += dt * 0.5 * (wt[prev] + wt[i])
                If_new = If + dt * 0.5 * (f[prev] + f[i])
                IIf += dt * 0.5 * (If + If_new)
                If = If_new
                IL += dt * 0.5 * (TL[prev] + TL[i])  # row k holds the load over [t_k, t_k+1): trapezoid is close
            u = (t[i] - t[s0]) / L_S
            cols.append([It, -Iw, w[i], -Iwt, wt[i], f[i], If, IIf, IL, 1.0, u, u * u])
            prev = i
        p = len(NAMES)
        g = [[0.0] * p for _ in range(p)]
        for v in cols:
            for a in range(p):
                va = v[a]
                ga = g[a]
                for b in range(a, p):
                    ga[b] += va * v[b]
        for a in range(p):
            for b in range(a):
                g[a][b] = g[b][a]
        G = {"n": n, "g": g}
        N = [IX["c1"], IX["u"], IX["u2"]]
        F = lambda G, extra=[]: fit(G, IX["w"], [IX["It"], IX["Iw"]] + N + extra)
        step_at = None
        if with_step:
            # suffix sums for the step column (u - u_k)+ ; candidates every ~1.5 % of the window, 5..95 %
            uu = [v[IX["u"]] for v in cols]
            S0 = [[0.0] * p for _ in range(n + 1)]
            S1 = [[0.0] * p for _ in range(n + 1)]
            for i in range(n - 1, -1, -1):
                v = cols[i]
                a0, a1, b0, b1 = S0[i + 1], S1[i + 1], S0[i], S1[i]
                ui = uu[i]
                for j in range(p):
                    b0[j] = a0[j] + v[j]
                    b1[j] = a1[j] + ui * v[j]
            base = F(G)
            best = None
            for k in range(int(0.05 * n), int(0.95 * n), max(1, n // 64)):
                uk = uu[k]
                gs = [S1[k][j] - uk * S0[k][j] for j in range(p)]
                ss = S0[k][IX["u2"]] - 2 * uk * S0[k][IX["u"]] + uk * uk * S0[k][IX["c1"]]
                g2 = [r + [gs[j]] for j, r in enumerate(g)] + [gs + [ss]]
                Gk = {"n": n, "g": g2}
                r = F(Gk, [STEP])
                if r and (best is None or r[3] < best[0]):
                    best = (r[3], k, Gk)
            if base and best and base[3] - best[0] > 25 * sig_w ** 2:
                step_at = best[1] * dt
                G = best[2]
                N = N + [STEP]
        res = {"t0": t[s0], "f_range": max(f[i] for i in idx) - min(f[i] for i in idx), "step": step_at}
        # speed-moved GLR as in windows.rs: drive torque + friction vs load alone, in σ²
        r_full = F(G)
        r_load = fit(G, IX["w"], N)
        res["moved"] = (r_load[3] - r_full[3]) / sig_w ** 2 if r_full and r_load else None
        X_f = [IX["It"], IX["Iw"]] + N
        X_r = [IX["w"], IX["Iw"]] + N
        fits = {
            "F": (r_full, jb_forward),
            "R": (fit(G, IX["It"], X_r), jb_reverse),
            "IV": (fit(G, IX["w"], X_f, [IX["f"], IX["If"]] + N), jb_forward),
            "IV2": (fit(G, IX["w"], X_f, [IX["If"], IX["IIf"]] + N), jb_forward),
            # diagnostics: forward with the true load integral as a regressor (the load's error removed)
            "F_TL": (fit(G, IX["w"], X_f + [IX["IL"]]), jb_forward),
            # forward/reverse on the noise-free speed (simulator truth): the price of speed noise
            "Ft": (fit(G, IX["wt"], [IX["It"], IX["Iwt"]] + N), jb_forward),
            "Rt": (fit(G, IX["It"], [IX["wt"], IX["Iwt"]] + N), jb_reverse),
        }
        for k, (r, fn) in fits.items():
            v = fn(r) if r else None
            res[k] = [x for x in v] if v else None
        # endogeneity diagnostic: correlation of ∫T_L and ∫τ after projecting out the nuisance and ∫ω
        g = G["g"]

        def resid_corr(a, b, on):
            ra, rb = fit(G, a, on), fit(G, b, on)
            if not ra or not rb:
                return None
            # cross-product of residuals: g_ab - beta_a' X'b
            Xb = [g[c][b] for c in on]
            Xa = [g[c][a] for c in on]
            XX = [[g[c][d] for d in on] for c in on]
            ea = ra[0]
            eb = rb[0]
            cab = g[a][b] - sum(ea[i] * Xb[i] for i in range(len(on))) - sum(eb[i] * Xa[i] for i in range(len(on))) \
                + sum(ea[i] * XX[i][j] * eb[j] for i in range(len(on)) for j in range(len(on)))
            return cab / math.sqrt(max(ra[3], 1e-300) * max(rb[3], 1e-300))
        c_ = resid_corr(IX["IL"], IX["It"], [IX["Iw"]] + N)
        res["corr_IL_It"] = c_ if c_ is not None and abs(c_) <= 1.0 + 1e-9 else None
        # the Gram matrix of the columns of interest with the window's nuisance partialled out (Schur complement),
        # for pooling windows as the RLS does (sum of their normal equations)
        A = [IX[k] for k in PART]
        NN = [[g[a][b] for b in N] for a in N]
        NNi = inverse(NN)
        if NNi is not None:
            AN = [[g[a][b] for b in N] for a in A]
            T = matmul(AN, NNi)
            res["part"] = [[g[A[i]][A[j]] - sum(T[i][k] * AN[j][k] for k in range(len(N))) for j in range(len(A))]
                           for i in range(len(A))]
        fo.write(json.dumps(res) + "\n")
    fo.close()


if __name__ == "__main__":
    main()
