"""The memory guard: what a rank may hold, shared by the run (``Solver``, which refuses a
system that cannot fit before allocating anything) and ``mpipack check`` (which estimates it)."""

# resident bytes per particle, a conservative estimate of the arrays (X^n, X^{n-1}, X^{n+1}, at
# the last build; gid, diameter; about 6 (2D) / 12 (3D) pair entries with growth room, each with
# the fire-al pass's terms and half list) and of the set-up's temporaries; measured at a packed
# state: 160 (2D) and 262 (3D) before the half list, which adds about 24 + 8 (b + 2) B an entry
# (56 B in 2D, 64 in 3D; 5.9 entries a sphere in 2D, 7.8 in 3D)
BYTES_PER_PARTICLE = {1: 300, 2: 500, 3: 850}
# bytes per pair-row entry at the peak of a build (entry 12 B, growth copies, temporaries); the
# fire-al pass's half list (24 + 8 (b + 2) B an entry, ``kernels.fire.pair_work``) is made only for rows of
# at most ``kernels.fire.HALF_LIST_MAX_ROW`` entries a sphere (in BYTES_PER_PARTICLE), never for
# a dense start's
BYTES_PER_ENTRY_PEAK = 40


def available_memory_bytes():
    """The node's MemAvailable (/proc/meminfo); 1 TiB where it cannot be read."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return 2 ** 40


def rank_budget_bytes(scene, ranks_per_node):
    """The bytes one rank may use: neighbor.max_pair_gib when the scene sets it (under a batch
    system's memory limit, set the key), else its share of the node's available memory."""
    gib = scene.neighbor.max_pair_gib
    return gib * 2 ** 30 if gib is not None else available_memory_bytes() / ranks_per_node
