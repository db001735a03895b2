"""Trace the shipped pile per step: v_y just before separation, overlap, energy, lift and budget.

Usage: python scripts/pile_trace.py PRESET [STEPS]  (env SLOP, MAXP: projection knobs of the
experiment commit). Prints every 40th step and a summary of steps >= 300.
"""
import sys, time
import numpy as np
from collision_node.physics.kernels import prepare
from collision_node.physics.scene import load_scene
from collision_node.physics.world import World
from collision_node.physics.accuracy import parse_accuracy
from collision_node.physics.reference import end_penetration
from collision_node.bench.pile import pile_quality

prepare()
preset = sys.argv[1]
steps = int(sys.argv[2]) if len(sys.argv) > 2 else 480
scene = load_scene('pile')
world = World(scene.with_accuracy(parse_accuracy(preset, 'x')))
print(world.explain())
sep = [s for s in world.pipeline.stages if s.name == 'separation'][0]
rec = {}
orig = sep.run
def run(ctx):
    v = ctx.state.velocity
    dyn = ctx.state.dynamic
    rec['vy_mean'] = float(v[dyn, 1].mean()); rec['vy_min'] = float(v[dyn, 1].min())
    rec['speed_max'] = float(np.linalg.norm(v[dyn], axis=1).max())
    before = ctx.state.position.copy()
    s0 = ctx.stats.dissipated.get('separation', 0.0)
    rec['budget'] = float(ctx.losses.sum()) if ctx.losses is not None else 0.0
    orig(ctx)
    from collision_node.physics.energy import lift
    rec['added'] = float(lift(ctx.state.inv_mass, ctx.state.position - before, ctx.effects.gravity).sum())
    rec['moved'] = float(np.abs(ctx.state.position - before).max())
    rec['sep'] = ctx.stats.dissipated.get('separation', 0.0) - s0
    rec['passes'] = getattr(sep, 'passes', -1)
sep.run = run
r = float(np.median(scene.initial.radius))
walls = scene.effects.walls
prevE = None
rows = []
t0 = time.process_time()
for k in range(steps):
    rec.clear()
    world.step()
    e = world.energy()
    E = e['total']
    q = pile_quality(world.state.position, world.state.velocity, world.state.radius, walls.low, walls.high, 2)
    rows.append((k, rec.get('vy_mean', np.nan), rec.get('vy_min', np.nan), rec.get('speed_max', np.nan), q['overlap_pairs_r'], q['overlap_walls_r'], E, rec.get('sep', 0.0), q['fastest'], rec.get('passes', -1), world.asleep_count, rec.get('budget', 0.0), rec.get('added', 0.0)))
cpu = time.process_time() - t0
for row in rows:
    if row[0] % 40 == 39 or row[0] >= steps - 3:
        print('step %3d vy_mean %+.4f vy_min %+.4f vmax %.4f ovl/r %.4f wall/r %.4f E %.3f sep %+.4f fastest %.4f passes %d asleep %d budget %.4f added %.4f' % row)
a = np.array(rows)
late = a[a[:, 0] >= 300]
print('late (steps 300..): vy_mean range %.4f..%.4f, vy_min min %.4f, max ovl/r %.4f, max dE step %.5f' % (
    np.nanmin(late[:, 1]), np.nanmax(late[:, 1]), np.nanmin(late[:, 2]), late[:, 4].max(), np.diff(late[:, 6]).max()))
print('E rises > 1e-9 after 300:', int((np.diff(late[:, 6]) > 1e-9).sum()), 'of', len(late) - 1)
print('total separation booked', world.stats.dissipated.get('separation', 0.0), 'balance', world.energy()['balance_error'])
print('cpu ms/step %.2f' % (1e3 * cpu / steps))
np.save('/tmp/overlap2/trace_%s.npy' % preset, a)
