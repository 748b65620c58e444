import math, random, sys, os, zlib
# (a reviewer's torque-driven plant, kept as written: plain Python; noise seeded by the kind and NOISE_SEED)
# pysim.py out.csv kind dur dt J B [J2@t] ; torque-driven recording with PI speed loop
out, kind, dur, dt, J, B = sys.argv[1], sys.argv[2], float(sys.argv[3]), float(sys.argv[4]), float(sys.argv[5]), float(sys.argv[6])
jsw = None
if len(sys.argv) > 7 and sys.argv[7]:
    a, b = sys.argv[7].split('@'); jsw = (float(b), float(a))
rnd = random.Random(zlib.crc32(kind.encode()) + int(os.environ.get('NOISE_SEED', '0')))
sn, tn = 0.8, 0.15
def setpoint(t):
    if kind == 'constspeed': return 40.0
    if kind in ('reverse', 'fanrev', 'overrun'):
        c = t % 16.0
        return 35.0 if c < 6 else (-35.0 if 8 <= c < 14 else 0.0)
    c = t % 20.0
    prog = [(0, 30), (4, 50), (7, 20), (10, None), (14, 45), (17, 10)]
    v = 30
    for (t0, s) in prog:
        if c >= t0:
            v = s if s is not None else 20 + (c - 10) / 4 * 30
    return v
def load(t, w, acc, sp_hist):
    if kind == 'chirp':
        # frequency sweeping 0.05 -> 2 Hz linearly over run, repeated
        f0, f1 = 0.05, 2.0; T = dur
        ph = 2 * math.pi * (f0 * t + (f1 - f0) * t * t / (2 * T))
        return 10 + 5 * math.sin(ph)
    if kind == 'accel': return 5 + 0.06 * acc            # looks like extra inertia 0.06
    if kind == 'accelpos': return 5 + 0.1 * max(acc, 0)  # only on speed-ups
    if kind == 'speedup_timed': return 5 + (3.0 if sp_hist else 0.0)
    if kind == 'overrun': return -8.0 + 0.0 * w          # driving load
    if kind in ('fanrev',): return 12 * (w / 40) * abs(w / 40)
    if kind == 'reverse': return 6 * math.copysign(1, w) if abs(w) > 0.5 else 6 * w / 0.5
    if kind == 'constspeed': return 10.0
    if kind == 'zero_then': return 0.0 if t < dur * 0.8 else 15.0
    if kind == 'jswitch': return 6.0 + 4 * (int(t / 3.3) % 3)
    if kind == 'square_fast': return 10.0 if (t % 0.5) < 0.25 else -2.0
    return 5.0
N = int(round(dur / dt)); sub = max(1, int(math.ceil(dt / 0.0002))); h = dt / sub
w = 0.0; integ = 0.0; Kp, Ki = 0.8 * J / 0.08, 8.0 * J / 0.08
Tmax = 80.0
last_sp = setpoint(0); sp_rise_t = -10
acc = 0.0
rows = []
for k in range(N + 1):
    t = k * dt
    Jt = J if (jsw is None or t < jsw[0]) else jsw[1]
    sp = setpoint(t)
    if sp > last_sp + 1e-9: sp_rise_t = t
    last_sp = sp
    e = sp - w
    Tcmd = Kp * e * 10 + integ
    Tcmd = max(-Tmax, min(Tmax, Tcmd))
    sp_hist = (t - sp_rise_t) < 0.8
    TL = load(t, w, acc, sp_hist)
    # record state at t and input applied over interval
    rows.append((t, w + rnd.gauss(0, sn), Tcmd + rnd.gauss(0, tn), w, TL, TL + rnd.gauss(0, 0.2)))
    for _ in range(sub):
        TLi = load(t, w, acc, sp_hist)
        a = (Tcmd - B * w - TLi) / Jt
        if kind in ('accel', 'accelpos'):
            # implicit: TL depends on acc; solve J a = T - Bw - 5 - c a  => a = (T-Bw-5)/(J+c)
            c = 0.06 if kind == 'accel' else 0.1
            a0 = (Tcmd - B * w - 5) / (Jt + c)
            a = a0 if (kind == 'accel' or a0 > 0) else (Tcmd - B * w - 5) / Jt
        acc = a
        w += h * a
    integ += Ki * e * dt * 10
    integ = max(-Tmax, min(Tmax, integ))
with open(out, 'w') as f:
    f.write('t_s,omega_rad_s,torque_nm,true_omega_rad_s,true_load_nm,load_nm\n')
    for r in rows: f.write(','.join(repr(round(x, 9)) for x in r) + '\n')
