"""What every entry of every observation version means, as data: ``(name, meaning, unit)`` per entry.

:func:`entry_table` lays them out for one layout (every index, with its meaning and unit); the generated env
pages (:mod:`cv2x_marl.env.pages`) print it. The layout itself (sizes, offsets) is
:class:`~cv2x_marl.env.observation.ObservationLayout`'s; the order here is the order the kernels write, and
``tests/env/test_pages.py`` checks the table covers every index of every registered id's observation.
"""

from __future__ import annotations

from typing import NamedTuple

from cv2x_marl.env.observation import CANDIDATE_NAMES, FEATURES, N_CANDIDATES, OWN, OWN_DRIVE, ObservationLayout

#: a length in units of the ``scale_m`` option
SCALE = "scale_m"
#: the entries of neighbour k (the k-th nearest other vehicle j), in the v0 block
V0_NEIGHBOUR = (
    ("dx", "position of j relative to the agent i, x", SCALE),
    ("dy", "position of j relative to i, y", SCALE),
    ("target", "1 if j is a target receiver of i's packets (not in i's subframe; Resource-v0: in link range)", "-"),
    ("nsv", "NSV_j: vehicles on i's resource within the interferer range of j (i excluded)", "vehicles"),
    ("has_interferer", "1 if j has a main interferer (NSV_j > 0)", "-"),
    ("interferer_dx", "position of j's main interferer relative to i, x (0 when none)", SCALE),
    ("interferer_dy", "position of j's main interferer relative to i, y (0 when none)", SCALE),
)
#: the agent's own entries closing the v0 block
V0_OWN = (
    ("x", "own position / the region's size, x", "-"),
    ("y", "own position / the region's size, y", "-"),
    ("drift_x", "own drift from the episode's start position, x", SCALE),
    ("drift_y", "own drift from the episode's start position, y", SCALE),
    ("elapsed", "elapsed share of the episode, t / max_cycles", "-"),
)
#: versions 1 and 2: per neighbour (with ``privileged`` a second entry follows each, block after block)
V1_NEIGHBOUR = (("model_p", "the two-distance model's predicted success of the link i -> j (eq. 15)", "-"),)
V1_PRIVILEGED = (("true_p", "the true expected success P_ij of the link i -> j (privileged)", "-"),)
#: versions 1 and 2: own entries (utilities per target receiver)
V1_OWN = (
    ("utility", "own utility now (eq. 12 per target receiver)", "-"),
    ("utility_change_x10", "10 x (utility now - utility a step ago)", "-"),
    ("utility_gain", "utility now - utility at the start", "-"),
    ("best_minus_now", "best utility of the episode - now (>= 0)", "-"),
    ("best_dx", "where the best was seen, relative to now, x", SCALE),
    ("best_dy", "where the best was seen, relative to now, y", SCALE),
    ("plan_dx", "the plan's position relative to now, x (v1: the model's best reachable; v2: sensing's)", SCALE),
    ("plan_dy", "the plan's position relative to now, y", SCALE),
    ("reach", "moving steps left x max_step_m", SCALE),
)
#: version 3: per neighbour, what i measured of j
V3_NEIGHBOUR = (
    ("rsrp", "RSRP of j measured at i over the sensing window, (dBm + 100) / 20; 0 when never heard", "-"),
    ("age", "periods since j's last decoded packet / sensing window", "-"),
    ("slot", "j's subframe (from its SCI) / RRI", "-"),
    ("subchannel", "j's sub-channel / sub-channels", "-"),
    ("co1_dx", "the co-channel vehicle nearest to j (on i's resource, not i nor j) relative to i, x", SCALE),
    ("co1_dy", "that vehicle relative to i, y", SCALE),
    ("co1", "1 if that vehicle exists", "-"),
    ("co2_dx", "the second nearest co-channel vehicle relative to i, x", SCALE),
    ("co2_dy", "that vehicle relative to i, y", SCALE),
    ("co2", "1 if that vehicle exists", "-"),
)
#: version 3: own entries
V3_OWN = (
    ("utility", "own utility now (eq. 12 per target receiver)", "-"),
    ("utility_change_x10", "10 x (utility now - utility a step ago)", "-"),
    ("drift_x", "own drift from the start, x", SCALE),
    ("drift_y", "own drift from the start, y", SCALE),
    ("time_left", "steps left / the horizon in force (max_cycles or a shorter TimeLimit)", "-"),
    ("reach", "moving steps left x max_step_m", SCALE),
)
#: version 4: per neighbour, what i measured of j on the road
V4_NEIGHBOUR = (
    ("rsrp", "RSRP of j over the packets i decoded in its sensing window, (dBm + 100) / 20; 0 when never heard", "-"),
    ("age", "periods since j's last decoded packet / sensing window", "-"),
    ("heard", "1 if i has heard j", "-"),
    ("slot", "j's subframe / RRI from its last decoded SCI (0 when never heard)", "-"),
    ("subchannel", "j's sub-channel / sub-channels from that SCI", "-"),
    ("release", "1 if that SCI announced a reselection", "-"),
    ("same_subframe", "1 if that subframe is i's next one (half duplex)", "-"),
    ("same_resource", "1 if that resource is i's next one (the packets collide)", "-"),
)
#: version 4: own entries
V4_OWN = (
    ("slot", "own next subframe / RRI", "-"),
    ("subchannel", "own next sub-channel / sub-channels", "-"),
    ("counter", "own reselection counter / its largest value", "-"),
    ("release", "1 if the own next SCI announces a reselection", "-"),
    ("utility", "own utility now (eq. 12 per target receiver)", "-"),
    ("utility_change_x10", "10 x (utility now - utility a step ago)", "-"),
)
#: version 5: the own entries after version 4's
V5_OWN = (
    ("decides", "1 if i reselected at the period's end: its action picks its resource this step", "-"),
    ("list_size", "entries of its candidate list / 20", "-"),
)
#: version 5: per candidate c (the c-th entry of i's list, in the standard's ranking: ascending S-RSSI), what i sensed
V5_CANDIDATE = (
    ("valid", "1 if c is an entry of the list (a survivor of the exclusion, TS 36.213 14.1.1.6 steps 5-7)", "-"),
    ("standard_list", "1 if c is among the entries the standard draws from (step 8)", "-"),
    ("rssi", "S-RSSI of c averaged over the sensing window, dB above the noise / 20", "-"),
    ("sci_rsrp", "RSRP of the strongest SCI reserving c, (dBm + 100) / 20; 0 when none was decoded", "-"),
    ("reserved", "1 if an SCI reserving c was decoded", "-"),
    ("users", "neighbours whose last decoded SCI reserves c / 4", "vehicles / 4"),
    ("user_dx", "the nearest of them relative to i (its CAM position), x (0 when none)", SCALE),
    ("user_dy", "that vehicle relative to i, y", SCALE),
    ("user_rsrp", "its RSRP measured at i, (dBm + 100) / 20 (0 when none)", "-"),
    (
        "subframe_users",
        "neighbours whose last decoded SCI is in c's subframe / 4 (they cannot hear i there)",
        "vehicles / 4",
    ),
    ("delay", "subframes from i's packet generation to c / the selection window's end", "-"),
    ("subchannel", "c's sub-channel / sub-channels", "-"),
)
assert tuple(name for name, _, _ in V5_CANDIDATE) == CANDIDATE_NAMES
#: the driving entries closing the vector with ``drive_observation``
DRIVE = (
    ("speed", "own speed / the speed limit", "-"),
    ("heading_x", "heading along the own lane, x (unit vector)", "-"),
    ("heading_y", "heading along the own lane, y", "-"),
    ("lane", "lane index / max(lanes per direction - 1, 1)", "-"),
    ("lane_left", "1 if a lane exists to the left", "-"),
    ("lane_right", "1 if a lane exists to the right", "-"),
    ("time_left", "steps left / the horizon in force", "-"),
)
#: each version's blocks after the v0 block: (per neighbour, own)
VERSION_ENTRIES = {
    0: ((), ()),
    1: (V1_NEIGHBOUR, V1_OWN),
    2: (V1_NEIGHBOUR, V1_OWN),
    3: (V3_NEIGHBOUR, V3_OWN),
    4: (V4_NEIGHBOUR, V4_OWN),
    5: (V4_NEIGHBOUR, V4_OWN + V5_OWN),
}


class Entry(NamedTuple):
    """One row of an observation table: the indices (``first`` .. ``last``, stepping by ``step``; one index when
    ``first == last``), the entry's name (``{k}``: the neighbour), meaning and unit."""

    first: int
    last: int
    step: int
    name: str
    meaning: str
    unit: str


def entry_table(layout: ObservationLayout) -> list[Entry]:
    """Every entry of ``layout``, in index order (per-neighbour entries as one row each, over k = 0 .. K - 1)."""
    k_n = layout.n_neighbours
    rows: list[Entry] = []

    def block(start: int, entries: tuple[tuple[str, str, str], ...], per_neighbour: bool) -> int:
        width = len(entries)
        for f, (name, meaning, unit) in enumerate(entries):
            if per_neighbour:
                rows.append(Entry(start + f, start + (k_n - 1) * width + f, width, f"{name}[k]", meaning, unit))
            else:
                rows.append(Entry(start + f, start + f, 1, name, meaning, unit))
        return start + (k_n if per_neighbour else 1) * width

    at = block(0, V0_NEIGHBOUR, True)
    assert at == k_n * FEATURES
    at = block(at, V0_OWN, False)
    assert at == k_n * FEATURES + OWN == layout.v0_size
    neighbour, own = VERSION_ENTRIES[layout.version]
    at = block(at, neighbour, True)
    if layout.privileged and layout.version in (1, 2):
        at = block(at, V1_PRIVILEGED, True)
    at = block(at, own, False)
    if layout.version == 5:  # the candidate block: one row per entry, over c = 0 .. N_CANDIDATES - 1
        width = len(V5_CANDIDATE)
        for f, (name, meaning, unit) in enumerate(V5_CANDIDATE):
            rows.append(Entry(at + f, at + (N_CANDIDATES - 1) * width + f, width, f"{name}[c]", meaning, unit))
        at += N_CANDIDATES * width
    if layout.drive:
        at = block(at, DRIVE, False)
    assert not layout.drive or len(DRIVE) == OWN_DRIVE
    return rows
