"""Every tunable of the solver, in one place: its unit, its default, what changing it does.

Stages and kernels read these names and define none of their own; the
compiled kernels take them as compile-time constants, so a change here
recompiles them (the kernel cache follows every physics source). Input
limits (largest coordinate, speed, count) live with the validation that
enforces them (``model/particles.py``, ``model/scene.py``).
"""

# --- Contact solve (stages/solve) ----------------------------------------------------------------

# Closing speeds below this fraction of the restitution threshold count as
# resolved, so sweeps over resting contact stop at rounding-level residues.
RESIDUAL_FRACTION = 1.0e-3

# Under gravity a contact whose normal, from the lower particle (or floor)
# to the upper one, points against gravity by at least this cosine supports
# the upper particle: a cold resting contact starts its solve from the share
# of the static load it carries (m g dt from above; 0.1 is 84 degrees off
# vertical). Side contacts below it carry no seed (the sweeps still solve
# them); 1 would seed only contacts straight below.
MIN_SUPPORT_ALIGNMENT = 0.1

# An impulse marks its particles struck (see _run_dissipative) only if its
# pair closed at this many times the restitution threshold. Closing speeds
# also build up inside a resting stack whose sweeps did not converge in the
# budget (in a column of 20 under `fast`: up to 8.7 times the threshold);
# passing those on as shocks made the stack bounce and gain energy through
# separation (measured: at factor 1 or 2 a column of 20 at e = 1 kept 0.2 to
# 0.7 m/s and a 200-disc pile gained 4.4e-3 J in a step; at 10 neither).
# The price: an impact slower than 10 thresholds (0.8 m/s at 240 Hz under
# 9.81 m/s^2) onto resting balls is not passed on through them.
STRIKE_FACTOR = 10.0

# Sweeps a contact solve may take (default 128, at most) when most of its
# touching resting contacts start cold, with no impulse cached from the
# previous step: a stack or pile built in place, an island just woken. Such a
# solve starts from the static loads alone (``_seed_loads``), and `fast`'s 8
# sweeps then build a pyramid's sideways thrust over several steps while it
# gives way (0.069 r without friction; 128 sweeps on the first step: 0.0025
# r). It still stops once converged; warm solves keep the preset's budget, and
# a preset whose own budget is at least this never changes it. More only
# costs time on cold starts.
COLD_START_SWEEPS = 128

# Share of the touching resting contacts that must start cold for that
# budget (default 0.5): a pour, whose few new contacts a step come in among
# warm ones, keeps the preset's budget.
COLD_START_SHARE = 0.5

# Speculative contacts, fraction of a radius (default 0.02). Under a
# restitution threshold a pair enters the step-end contact solve while its
# gap is below the distance it closes in a step at the threshold speed
# (threshold x dt, m) plus this fraction of the mean of its two radii (a
# particle and a wall plane: of its radius), and the solve lets it close by
# at most its gap in the next step (v_n >= -gap / dt), so resting contact
# is held before it overlaps. The margin catches pairs the solve's own
# impulses set closing. Larger: more contacts per step (each a dot product
# per sweep); 0: only contacts within threshold x dt.
SPECULATIVE_MARGIN = 0.02

# A particle within this fraction of its radius, plus WALL_ULPS floating-point
# spacings at the plane's coordinate, of a wall plane touches it (the walls
# stage places resting particles on the plane to rounding). Never a fraction
# of the coordinate itself: 1e-9 of a plane at x = 1e9 m was a slop of 1 m.
WALL_SLOP = 1.0e-9

WALL_ULPS = 4.0

# --- Swept contacts (stages/swept) ---------------------------------------------------------------

# Under gravity, a pair (or a particle and a wall) closer than this fraction
# of its contact distance at the step start is in resting contact (see
# SweptContactStage._in_contact).
TOUCH_SLOP = 1.0e-6

# Relative margin of ``_out_of_reach``: far above the rounding of its
# distance test (a few ulps) and of the root ``pair_time`` computes (at worst
# about 3e-8 relative, for a grazing pair, where its discriminant cancels).
REACH_MARGIN = 1.0e-6

# Bisection steps that finish a root the closed form or the eigenvalues only
# bracket (the parabola-sphere quartic of the swept stage and ``law/paths``).
BISECTIONS = 60

# --- Separation (stages/correction) --------------------------------------------------------------

# Projection passes per step under gravity: the accuracy setting
# ``separation_passes`` (model/accuracy.py; one pass without gravity).

# Of r: under gravity, a particle this close to a floor plane (or to a
# particle below it) rests on it: the contact solve seeds a cold contact
# with the static load, and separation's pushes travel away from the supports: each pair's particle
# nearer a support (in contacts) holds and the other takes the whole push,
# so one pass lifts a column's overlap off its floor instead of pressing the
# lower particle into it. Larger counts hovering particles as supported
# (they hold, their partners move); 0 counts only particles on the plane.
SUPPORT_SLOP = 0.01

# Cosine: separation holds the particle nearer a support only where the pair
# stands one above the other, its line of action within this of vertical
# (0.5: 60 degrees, so a hexagonal pile's grooves hold); side contacts share
# the push by inverse mass. 1 holds only straight columns: a pyramid of 55
# discs then collapses under `fast` and the shipped pile settles 20 times
# deeper (docs/stability.md, "Dense contact").
STACK_ALIGNMENT = 0.5

# Sweeps, at most, that separation spends lifting each particle out of all
# the supports it stands on at once (a disc in a groove rises straight up
# instead of walking sideways). Each sweep shrinks the error by the squared
# cosine between two supports' normals: 1/4 in a hexagonal groove, so 16
# sweeps leave 2e-10 of the lift. More only costs time where supports are
# nearly parallel.
SUPPORT_SWEEPS = 16

# Of r: those sweeps stop once no push changes by more than this.
SUPPORT_TOLERANCE = 1e-9

# --- Broadphase (stages/detection) ---------------------------------------------------------------

# Reaches within one size class differ by less than this factor: the
# searches of a class overshoot by at most this ratio in distance.
CLASS_RATIO = 2.0

# Skin of the Verlet list: about SKIN_STEPS steps of travel at the rms speed,
# at most SKIN_MAX_RADII median radii (a wider skin costs more pairs than
# the searches it saves), at least SKIN_MIN_RADII of them.
SKIN_STEPS = 20.0

SKIN_MAX_RADII = 1.5

SKIN_MIN_RADII = 0.05

# Search afresh once more than this share of the particles are movers.
MAX_MOVER_SHARE = 0.02

# Up to this many particles every pair is a candidate: cheaper than any
# search for the handful of bodies of a cradle or a billiards table.
ALL_PAIRS_UP_TO = 48

# The relative slack of the pair test (``broadphase.QUERY_SLACK``, same value).
PAIR_SLACK = 1e-9

# Cell search boxes are widened by this much more: the exact test above
# passes pairs up to the slack beyond reach_i + reach_j, and the box must
# hold them all after the rounding of (x - corner) / cell.
SCAN_SLACK = 1e-6

# Cells are at least extent / 2^40 wide: integer cell indices stay < 2^41.
MAX_CELLS_PER_AXIS = 2.0 ** 40

# Cell width in the class's largest reach: 2 scans 3 cells per axis, 1 scans
# 5 smaller ones (a box closer to the sphere searched: fewer candidates).
CELL_REACHES = 2.0

# A class whose occupied box has at most this many cells per particle (plus
# a few) gets a dense table: no hashing, rows of cells read in one range.
DENSE_CELLS_PER_ITEM = 16.0

# Cells are this much wider than CELL_REACHES reaches: a search (at most two
# reaches plus SCAN_SLACK) then stays within one cell of the query's cell
# even after the rounding of (x - corner) / cell (at most about 2^-24 cells
# in a dense table), so a dense class can scan its neighbour cells without
# computing the search box (``_dense_pairs``).
CELL_MARGIN = 4e-6

# The bound on the cells per axis that rounding argument assumes.
DENSE_AXIS_CELLS = 2 ** 24

# --- Spatial order of the rows (stages/ordering) -------------------------------------------------

# A world of at least this many particles (default 50,000) keeps its rows in
# cell order: at each full pair search the rows are renumbered along space
# (the ids stay), so neighbours sit near each other in memory and every pair
# reads its partner from nearby. A smaller world keeps its rows in id order,
# where a random order costs little (its arrays fit the caches). Lower it
# and a mid-sized world runs in a different (equally valid) contact order.
SPATIAL_ORDER_MIN_PARTICLES = 50_000

# Side of the cells the rows are ordered by, in mean radii (default 4): each
# cell's rows are contiguous, cells by z, then y, then x. At most
# SPATIAL_ORDER_CELLS_PER_PARTICLE cells per particle: a sparser world gets
# wider cells, so the ordering's work and memory stay proportional to n.
SPATIAL_ORDER_CELL_RADII = 4.0

SPATIAL_ORDER_CELLS_PER_PARTICLE = 2.0

# --- Memory of a step (stages/detection) ---------------------------------------------------------

# The most memory a step's candidate pairs may take, bytes (default 2 GiB).
# A world whose broadphase would hold more (particles piled on each other,
# or a swept reach |v| dt far wider than the particles, even searched along
# their paths) is refused at the request (scene load, spawn, accuracy) or
# at the step with ``broadphase.StepTooLarge``, saying how many pairs it
# would need; it never takes the process down. More admits denser or
# faster worlds on a machine with the memory for them.
STEP_MEMORY_BUDGET = 2 * 1024 ** 3

# What one candidate pair may cost across a step's buffers, bytes (an upper
# estimate: the broadphase's search, sort, list and merge and the swept
# contacts' arrays took about 40 at the peak of a balanced step, the discrete
# narrowphase adds 48 per candidate; the rest is room for buffers that grow).
# The budget over this is the most pairs a search may hold
# (``broadphase.MAX_PAIRS``, 8.4e6 by default).
PAIR_BYTES = 256

# The most pair tests a search along paths makes before it gives up (about
# a second of compiled tests): bounds the time a refusal takes.
MAX_PATH_TESTS = 200_000_000

# Slack of the path test, in the length of the pair's relative path over the
# step: far above the rounding of the closest approach d + s u.
PATH_SLACK = 1e-9

# --- Event-driven exact mode (stages/events) -----------------------------------------------------

# Cells hold about this many particles (cells are never narrower than a
# contact diameter): fewer means more cell crossings, more means more
# neighbours per prediction. A crossing predicts only the newly entered layer
# of cells, so small cells pay: 0.25 was about the fastest of 1, 0.7, 0.5,
# 0.35, 0.25 and 0.1 (docs/performance.md).
PARTICLES_PER_CELL = 0.25

# Steps in a row that go straight to the step solver after fallbacks, at most.
MAX_FALLBACK_HOLD = 63

# Pair impacts a particle's candidate list holds: one more drops the latest
# and schedules a fresh prediction of the particle at its time (nothing is
# lost; a longer list means fewer refreshes and longer scans per event).
CANDIDATES = 8

# Slots of the cell table per particle, at most (an open scene that spreads
# out shares slots between far cells; the neighbour query tells them apart).
SLOTS_PER_PARTICLE = 8

# A contact rests when its gap is at most this fraction of r_i + r_j ...
RESTING_GAP = 1e-9

# ... plus this many floating-point spacings of the largest coordinate involved.
RESTING_ULPS = 64.0

# Resting partners a particle can hold (12 touch an equal sphere in 3-D;
# overlapping or mixed sizes can touch more). More ends the exact attempt.
PARTNERS = 16

# Both solves sweep over-relaxed to their tolerance, then plainly (Gauss-
# Seidel) to it again: a chain or a pile of n rows needs about n^2 plain
# sweeps but about n over-relaxed ones (the 500-disc pile: 2,000 to 5,000
# plain sweeps a step, measured), and the plain ones leave a lone contact
# solved exactly (a ball on a floor: speed and acceleration exactly 0).
OVER_RELAXATION = 1.6

# Sweeps end when no resting normal speed exceeds this fraction of the
# resting speed, and when no force changes any relative acceleration by
# more than this fraction of |g|; at most MAX_SWEEPS of each.
# (1e-11 |g| leaves a packed pile sinking into itself by ½ 1e-10 dt^2,
# 1e-15 m a step at 240 Hz; 1e-13 |g| cost the 500-disc pile 3 to 6 times
# the sweeps.)
VELOCITY_TOLERANCE = 1e-12

ACCELERATION_TOLERANCE = 1e-11

MAX_SWEEPS = 20000

# --- Drag (stages/motion) ------------------------------------------------------------------------

# Below this lambda dt, (dt - phi) / lambda uses its Taylor series (the
# closed form cancels there); the first term left out is below 5e-14
# relative, as is the cancellation error just above the limit.
SERIES_LIMIT = 1.0e-2

# --- Sleeping islands (stages/sleeping) ----------------------------------------------------------

# Particles closer than this share of their radii sum (gap) are in contact
# for islands and waking: resting contacts end a step touching up to the
# solver's slop, and the broadphase's list always holds pairs this near.
CONTACT_MARGIN = 0.02

# Up to this many (awake, sleeping) pairs the wake stage tests every pair
# directly; beyond, a k-d tree of the sleepers finds the candidates.
DIRECT_PAIRS = 1 << 15

# --- Restitution threshold (model/effects) -------------------------------------------------------

# Default restitution threshold under gravity, in multiples of |g| dt: the
# closing speed gravity builds in one or two steps of resting contact is
# treated as resting (perfectly inelastic), so a resting pile does not
# micro-bounce.
GRAVITY_THRESHOLD_STEPS = 2.0

# --- Colouring (law/coloring) --------------------------------------------------------------------

# Box2D v3 uses 24 colours; a bitmask per particle holds up to 64.
MAX_COLORS = 32

# --- Backends ----------------------------------------------------------------------------------

# How a stage may run: its compiled kernels (the default and what every preset
# uses) or the vectorised numpy law (the tests' reference).
BACKENDS = ('kernel', 'numpy')

# --- Memory (step/memory.py) ---------------------------------------------------------------------

# Keep freed memory in the process for the next step (glibc's malloc;
# default True): a step of a large world frees and allocates arrays of
# every particle's size, and pages returned to the system fault again when
# touched (3 to 5 ms a step after each broadphase rebuild of a 100,000-
# particle gas here). False leaves the allocator's own policy.
KEEP_FREED_MEMORY = True
# Blocks up to this size come from the heap and are reused, not from a fresh
# mmap returned on free (bytes, default 32 MiB, glibc's largest; glibc's own
# default starts at 128 KiB).
ALLOCATOR_MMAP_THRESHOLD = 32 * 2 ** 20
# Free memory at the top of the heap is returned to the system only past this
# (bytes, default 2 GiB - 1, the most mallopt takes: its value is a C int;
# glibc's own 128 KiB). The process's resident memory stays near its peak.
ALLOCATOR_TRIM_THRESHOLD = 2 ** 31 - 1

# --- Threads (step/threads.py) -----------------------------------------------------------------

# A kernel loop runs on several threads only over at least this many items
# (particles or pairs, default 4096); shorter loops run on the calling
# thread. Starting a parallel region costs a few microseconds, about what
# 100 to 300 items of a loop cost, so a small scene (a 240-disc pile) would
# pay more to share its loops than it saves. It decides where a loop runs,
# never what it computes, with one exception: a contact solve of at least
# this many pairs visits them colour by colour at every thread count (the
# order a shared solve needs, so that one thread gives the same result),
# a smaller one in the broadphase's pair order.
PARALLEL_MIN_ITEMS = 4096
# Items per block of a parallel loop that gathers what it keeps (pairs that
# overlap, pairs near each other): each block fills its own slice, then the
# blocks are joined in order, so the list is the serial loop's whatever
# thread ran which block (default 2048; any value, the same results).
PARALLEL_BLOCK_ITEMS = 2048
# Pairs of one colour the contact solve visits on several threads (default
# 256); a smaller colour is visited on the calling thread (the same
# result: the pairs of a colour share no dynamic particle).
PARALLEL_MIN_BATCH = 256
# Pairs of a colour one thread visits at a time (default 64): small enough
# that a colour of a few hundred pairs spreads over every thread.
PARALLEL_SOLVE_BLOCK = 64
# Most threads a world may be given (the runner's --threads, the node's
# threads parameter, the benchmarks' --threads); numba's pool is sized once
# per process (NUMBA_NUM_THREADS, default the machine's cores), so a count
# over the pool is refused with what the pool holds.
MAX_THREADS = 1024
