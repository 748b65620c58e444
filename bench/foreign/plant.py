import sys
# (a reviewer's plant-file writer, kept as written)
# plant.py out.toml key=value ...  keys: J B Dp Dm V beta leak back pn sn ln sample_ms maxhz ramp tc pp; load="..." (toml body lines separated by ;) ; eff="..." ; est="..."
kv = dict(a.split('=', 1) for a in sys.argv[2:])
g = lambda k, d: kv.get(k, d)
s = f"""[drive]
pole_pairs = {g('pp','2')}
ramp_hz_per_s = {g('ramp','25.0')}
time_constant_s = {g('tc','0.02')}
max_hz = {g('maxhz','60.0')}
comm_timeout_ms = 1000

[pump]
displacement_cm3 = {g('Dp','16.0')}

[motor]
displacement_cm3 = {g('Dm','32.0')}
inertia_kg_m2 = {g('J','0.08')}
viscous_nm_s_rad = {g('B','0.04')}

[hydraulics]
volume_l = {g('V','0.3')}
bulk_modulus_bar = {g('beta','15000.0')}
back_pressure_bar = {g('back','3.0')}
leakage_l_min_per_bar = {g('leak','0.02')}

[sensors]
pressure_noise_bar = {g('pn','0.3')}
speed_noise_rad_s = {g('sn','0.8')}
load_noise_nm = {g('ln','0.2')}
sample_ms = {g('sample_ms','1.0')}

[load]
""" + g('load', 'kind = "recorded"').replace(';', '\n') + "\n"
if 'eff' in kv:
    s += "\n" + kv['eff'].replace(';', '\n') + "\n"
if 'est' in kv:
    s += "\n[estimator]\n" + kv['est'].replace(';', '\n') + "\n"
open(sys.argv[1], 'w').write(s)
