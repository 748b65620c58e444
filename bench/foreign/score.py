import csv, math, sys
# (a reviewer's scoring script, kept as written: plain Python, no numpy)
# usage: score.py rec.csv est_rls.csv est_kf.csv trueJ trueB [label] [Jsched]
# Jsched: optional "t1:J1" meaning true J switches to J1 at t1
def load(p):
    with open(p) as f:
        r = csv.reader(f); h = next(r); rows = [x for x in r]
    return h, rows
def num(s):
    if s == '' : return None
    try: return float(s)
    except: return None
rec_h, rec = load(sys.argv[1]); rh, rr = load(sys.argv[2]); kh, kr = load(sys.argv[3])
J = float(sys.argv[4]); B = float(sys.argv[5]); label = sys.argv[6] if len(sys.argv) > 6 else ''
sched = None
if len(sys.argv) > 7 and sys.argv[7]:
    a, b = sys.argv[7].split(':'); sched = (float(a), float(b))
defects = []
for name, h, rows in (('rls', rh, rr), ('kf', kh, kr)):
    bad = 0; big = 0
    for i, row in enumerate(rows):
        for c, v in zip(h, row):
            if v == '': continue
            x = num(v)
            if x is None or not math.isfinite(x):
                bad += 1
                if bad <= 3: defects.append(f'{name} row {i} col {c} = {v!r}')
            elif abs(x) > 1e5 and c not in ('t_s',):
                big += 1
                if big <= 3: defects.append(f'{name} row {i} col {c} = {v} (absurd?)')
    if bad: defects.append(f'{name}: {bad} non-finite cells')
    if big: defects.append(f'{name}: {big} cells >1e5')
if len(rr) != len(rec) or len(kr) != len(rec):
    defects.append(f'row counts rec {len(rec)} rls {len(rr)} kf {len(kr)}')
ti = rec_h.index('true_load_nm'); tti = rec_h.index('t_s')
ri = {c: rh.index(c) for c in rh}; ki = kh.index('load_hat_nm')
se_r = se_k = 0.0; n = 0
cov = {}; jerr_max = 0.0; jid = 0; jbad = 0; bid = 0
tmax = None
for k in range(min(len(rec), len(rr), len(kr))):
    tl = num(rec[k][ti]); lr = num(rr[k][ri['load_hat_nm']]); lk = num(kr[k][ki])
    t = num(rr[k][0])
    if tl is None or lr is None or lk is None: continue
    se_r += (lr - tl) ** 2; se_k += (lk - tl) ** 2; n += 1
    Jt = J
    if sched and t is not None and t >= sched[0]: Jt = sched[1]
    jh = num(rr[k][ri['inertia_hat_kg_m2']]); jid_c = num(rr[k][ri['inertia_identified']])
    if jid_c == 1:
        jid += 1; e = abs(jh / Jt - 1); jerr_max = max(jerr_max, e)
        if e > 0.15: jbad += 1
    if num(rr[k][ri['viscous_identified']]) == 1: bid += 1
rm_r = math.sqrt(se_r / max(n, 1)); rm_k = math.sqrt(se_k / max(n, 1))
# coverage at times
tlast = num(rr[-1][0])
times = [15, 30, 45, 60, 120, 300, 600, 1200, 1800]
times = [x for x in times if x <= tlast] + [tlast]
covs = []
for T in times:
    # find first row with t >= T
    row = None
    for r in rr:
        tv = num(r[0])
        if tv is not None and tv >= T - 1e-9: row = r; break
    if row is None: row = rr[-1]
    Jt = J
    if sched and T >= sched[0]: Jt = sched[1]
    jh = num(row[ri['inertia_hat_kg_m2']]); js = num(row[ri['inertia_sd_kg_m2']]); jc = num(row[ri['inertia_identified']])
    bh = num(row[ri['viscous_hat_nm_s_rad']]); bs = num(row[ri['viscous_sd_nm_s_rad']]); bc = num(row[ri['viscous_identified']])
    okJ = (jc != 1) or abs(jh - Jt) <= 2 * js
    okB = (bc != 1) or abs(bh - B) <= 2 * bs
    # strict: within 2 sd regardless
    sJ = abs(jh - Jt) <= 2 * js; sB = abs(bh - B) <= 2 * bs
    covs.append(f'{T:g}s:J{jh/Jt:.2f}x({int(jc)}{"" if okJ else "!"}{"" if sJ else "o"}) B{bh/B if B else float("nan"):.2f}x({int(bc)}{"" if okB else "!"}{"" if sB else "o"})')
ratio = rm_r / rm_k if rm_k > 0 else float('nan')
print(f'{label}\tn={n}\trls={rm_r:.3f}\tkf={rm_k:.3f}\tratio={ratio:.3f}{" HARM" if ratio>1.05 else ""}\tJid_rows={jid}\tJid>15%={jbad}\tJerrmax={jerr_max:.3f}\tBid_rows={bid}\t' + ' '.join(covs))
for d in defects: print('  DEFECT?', d)
