"""The sections of the scenario configuration: one frozen :class:`~cv2x_marl.schema.Section` per part of the
simulator (road, vehicles, radio, channel, traffic, sps, link, metrics, sim), each key's unit, range or choices and
description in its field metadata, and the names the keys' choices come from (PER_CURVES, PER_INTERPOLATIONS,
TRUTH_LOS).

:mod:`cv2x_marl.config` composes them into :class:`~cv2x_marl.config.ScenarioConfig` and re-exports every name
here; import them from there.
"""

from __future__ import annotations

from dataclasses import dataclass

from cv2x_marl.schema import ConfigError, Section, key_field

#: the most vehicles a scenario may have (also the cap on density x road length)
MAX_VEHICLES = 100_000


@dataclass(frozen=True)
class RoadConfig(Section):
    """Road geometry (paper Sec. 3, Fig. 1; 3GPP TR 36.885 Annex A.1.2)."""

    _name = "road"
    kind: str = key_field(
        "grid", "Road layout: Manhattan grid (paper) or straight highway", choices=("grid", "highway")
    )
    length_m: float = key_field(450.0, "Grid: side of the square region; highway: road length", "m", 50.0, 1e6)
    n_roads_per_axis: int = key_field(4, "Grid: number of horizontal (and of vertical) two-way roads", "", 1, 50)
    lanes_per_direction: int = key_field(1, "Lanes in each direction of every road", "", 1, 8)
    lane_width_m: float = key_field(3.5, "Lane width", "m", 1.0, 10.0)
    p_straight: float = key_field(0.5, "Grid: probability of going straight at a crossing", "", 0.0, 1.0)
    p_left: float = key_field(0.25, "Grid: probability of turning left at a crossing", "", 0.0, 1.0)
    p_right: float = key_field(0.25, "Grid: probability of turning right at a crossing", "", 0.0, 1.0)
    wrap_distances: bool = key_field(
        False,
        "Measure distances on the torus (minimum image). False: plain Euclidean distances in the "
        "region (the paper's RoI, with edge effects); mobility always wraps around",
    )

    def _check(self) -> None:
        total = self.p_straight + self.p_left + self.p_right
        if abs(total - 1.0) > 1e-9:
            raise ConfigError(
                f"road.p_straight + road.p_left + road.p_right must be 1, got {total:g} "
                f"({self.p_straight:g} + {self.p_left:g} + {self.p_right:g})"
            )


@dataclass(frozen=True)
class VehiclesConfig(Section):
    """Vehicle population and speeds."""

    _name = "vehicles"
    n_vehicles: int = key_field(21, "Number of vehicles (ignored when density_veh_per_m is set)", "", 2, MAX_VEHICLES)
    density_veh_per_m: float | None = key_field(
        None,
        "Vehicles per metre of road, all lanes and directions together; null: use n_vehicles",
        "veh/m",
        0.0,
        10.0,
        lo_open=True,
    )
    placement: str = key_field(
        "random",
        "random: uniform position on a random lane; uniform: equal spacing along each lane",
        choices=("random", "uniform"),
    )
    speed_min_mps: float = key_field(4.17, "Lowest vehicle speed (drawn uniformly per vehicle)", "m/s", 0.0, 100.0)
    speed_max_mps: float = key_field(16.67, "Highest vehicle speed", "m/s", 0.0, 100.0)
    mobility: str = key_field(
        "model",
        "Where vehicle motion comes from: model: the random-speed lane model with wrap-around; sumo: a SUMO "
        "scenario stepped in lockstep through libsumo (vehicles.sumo_config, or one generated from the road "
        "section); trace: replay of a SUMO FCD trace (vehicles.trace_file). sumo and trace track the first "
        "N vehicles in the network (docs/mobility.md; the 'sumo' extra)",
        choices=("model", "sumo", "trace"),
    )
    sumo_config: str | None = key_field(
        None,
        "vehicles.mobility=sumo: the SUMO scenario (.sumocfg) to run; null: generate one from the road section "
        "(road.kind=grid; random-walk demand of N vehicles at speeds in [speed_min_mps, speed_max_mps])",
        allowed="path to a .sumocfg file, or null",
    )
    trace_file: str | None = key_field(
        None,
        "vehicles.mobility=trace: a SUMO FCD trace (XML from --fcd-output, or parquet with columns time, id, "
        "x, y, angle, speed), interpolated linearly to traffic.rri_ms",
        allowed="path to an .xml or .parquet file, or null",
    )
    population: str = key_field(
        "fixed",
        "fixed: the same N vehicles for the whole run (sumo and trace: the first N in the network); open: "
        "vehicles enter and leave the scenario (sumo and trace only): an entering vehicle listens for one "
        "reservation period, then selects a resource by sensing; a leaving vehicle's links end. With open, "
        "n_vehicles (or density_veh_per_m) is the mean count a generated demand aims at and vehicles.capacity "
        "bounds how many may be present at once (docs/mobility.md)",
        choices=("fixed", "open"),
    )
    capacity: int | None = key_field(
        None,
        "vehicles.population=open: the most vehicles present at once (the simulator's array size); null: "
        "2 x the resolved vehicle count + 16",
        "",
        2,
        MAX_VEHICLES,
    )
    sumo_begin_s: float | None = key_field(
        None,
        "SUMO time at which the run starts (sumo and trace; the scenario is stepped until then); null: 0 with "
        "population=fixed, road.length_m / vehicles.speed_min_mps (a slow vehicle crossing the region once, so the "
        "roads fill) with population=open",
        "s",
        0.0,
        86400.0,
    )

    def _check(self) -> None:
        if self.speed_min_mps > self.speed_max_mps:
            raise ConfigError(
                f"vehicles.speed_min_mps ({self.speed_min_mps:g}) must not exceed "
                f"vehicles.speed_max_mps ({self.speed_max_mps:g})"
            )
        if self.mobility == "trace" and not self.trace_file:
            raise ConfigError("vehicles.mobility=trace needs vehicles.trace_file (the FCD trace to replay)")
        for key in ("sumo_config", "trace_file"):
            value = getattr(self, key)
            if value is not None and not value.strip():
                raise ConfigError(f"vehicles.{key}: an empty path; give a file or null")
        if self.population == "open" and self.mobility == "model":
            raise ConfigError(
                "vehicles.population=open needs vehicles.mobility=sumo or trace (the lane model keeps its vehicles: "
                "they wrap around the region)"
            )
        if self.capacity is not None and self.population != "open":
            raise ConfigError(
                f"vehicles.capacity={self.capacity} sizes an open population's slots; with "
                "vehicles.population=fixed the vehicle count is vehicles.n_vehicles (set capacity to null, "
                "or population to open)"
            )


@dataclass(frozen=True)
class RadioConfig(Section):
    """Transmitter and receiver radio parameters (paper Table 1)."""

    _name = "radio"
    tx_power_dbm: float = key_field(26.0, "Transmit power s (paper Table 1)", "dBm", -30.0, 46.0)
    carrier_hz: float = key_field(2.0e9, "Carrier frequency c (eq. 4; WINNER+ B1 valid 2-6 GHz)", "Hz", 1e8, 1e11)
    noise_dbm: float = key_field(
        -112.45, "Noise power n_p over one subchannel, before the noise figure (paper Table 1)", "dBm", -200.0, 0.0
    )
    noise_figure_db: float = key_field(9.0, "Receiver noise figure (added to noise_dbm)", "dB", 0.0, 30.0)
    tx_antenna_gain_dbi: float = key_field(3.0, "Transmit antenna gain (TR 36.885: 3 dBi)", "dBi", -20.0, 30.0)
    rx_antenna_gain_dbi: float = key_field(3.0, "Receive antenna gain (TR 36.885: 3 dBi)", "dBi", -20.0, 30.0)
    sensitivity_dbm: float | None = key_field(
        None, "Receptions with a received power below this fail; null: no floor", "dBm", -200.0, 0.0
    )


@dataclass(frozen=True)
class ChannelConfig(Section):
    """Propagation: path loss (eq. 3 or WINNER+ B1), shadowing, fast fading."""

    _name = "channel"
    pathloss: str = key_field(
        "winner_b1",
        "Path-loss model: power law of eq. 3, or WINNER+ B1 (TR 36.885)",
        choices=("power_law", "winner_b1"),
    )
    power_law_k_db: float | None = key_field(
        None, "Eq. 3 gain K at d0 in dB (negative); null: free-space gain at d0 for the carrier", "dB", -200.0, 0.0
    )
    power_law_d0_m: float = key_field(1.0, "Eq. 3 reference distance d0", "m", 0.01, 1000.0, lo_open=True)
    power_law_exponent: float = key_field(2.0, "Eq. 3 exponent omega (2: free space)", "", 1.0, 8.0)
    effective_height_m: float = key_field(
        1.5,
        "WINNER+ B1 effective antenna height h' of both ends (implementations use 0.5 or 1.5)",
        "m",
        0.1,
        10.0,
    )
    min_distance_m: float = key_field(
        3.0, "Distances below this are clipped for path loss (TR 36.885)", "m", 0.1, 100.0
    )
    los: str = key_field(
        "geometry", "LOS/NLOS from the grid geometry (same street = LOS), or LOS always", choices=("geometry", "always")
    )
    shadowing_std_db: float = key_field(3.0, "Log-normal shadowing std in LOS (0 disables shadowing)", "dB", 0.0, 20.0)
    shadowing_nlos_std_db: float = key_field(4.0, "Log-normal shadowing std in NLOS", "dB", 0.0, 20.0)
    shadowing_decorrelation_m: float = key_field(
        10.0, "Shadowing decorrelation distance (10 urban, 25 highway)", "m", 0.1, 1e4, lo_open=True
    )
    shadowing_correlation: str = key_field(
        "pair_distance",
        "What the shadowing of a pair decorrelates with, rho = exp(-D / shadowing_decorrelation_m): pair_distance: "
        "D = the change of the pair's distance since its last update (TR 36.885 A.1.4; the default); travelled: D "
        "= the sum of the distances both vehicles travelled (the paper presets' simplification)",
        choices=("travelled", "pair_distance"),
    )
    fading: str = key_field(
        "none", "Fast fading per transmission: none or Rayleigh (|h|^2 ~ Exp(1))", choices=("none", "rayleigh")
    )


@dataclass(frozen=True)
class TrafficConfig(Section):
    """Periodic packet generation."""

    _name = "traffic"
    rri_ms: int = key_field(100, "Resource reservation interval = packet period (1 subframe = 1 ms)", "ms", 20, 1000)
    packet_bytes: int = key_field(
        190, "Packet size (selects the PER curve family; one subchannel per packet)", "B", 1, 10000
    )
    synchronous: bool = key_field(
        True,
        "All vehicles generate their packets in the same subframe of each period, so all select from "
        "the same selection window (the paper's pool of 8 subframes x 2 subchannels); false: random offset",
    )


@dataclass(frozen=True)
class SpsConfig(Section):
    """Sensing-based semi-persistent scheduling (TS 36.213 14.1.1.6, TS 36.321 5.14.1.1)."""

    _name = "sps"
    n_subchannels: int = key_field(2, "Subchannels per subframe (paper Table 1: 2)", "", 1, 50)
    subchannel_rbs: int = key_field(10, "Resource blocks per subchannel (RSRP is per resource element)", "RB", 1, 100)
    t1_subframes: int = key_field(1, "Selection window start T1 after packet generation", "subframes", 1, 4)
    selection_window_subframes: int = key_field(
        8, "Selection window length T2 - T1 + 1 (paper Table 1: 8)", "subframes", 1, 1000
    )
    sensing_window_ms: int = key_field(1000, "Sensing window over which S-RSSI is averaged", "ms", 100, 10000)
    rsrp_threshold_dbm: float = key_field(-110.0, "Initial PSSCH-RSRP exclusion threshold (per RE)", "dBm", -140.0, 0.0)
    threshold_step_db: float = key_field(3.0, "Threshold increase while too few candidates remain", "dB", 0.1, 20.0)
    min_candidate_fraction: float = key_field(0.2, "Share of candidates that must survive exclusion", "", 0.01, 1.0)
    selection: str = key_field(
        "paper",
        "paper: best 3 by RSSI, one at random; 3gpp: lowest-RSSI 20 %, one at random; uniform: one at random "
        "among every candidate that survives the exclusion, no S-RSSI ranking (the analytical model's assumption, "
        "Gonzalez-Martin et al. 2019 eq. 26: uniform among its N_c candidates; not the standard's step 8)",
        choices=("paper", "3gpp", "uniform"),
    )
    threshold_increase: str = key_field(
        "3gpp",
        "3gpp: while fewer than min_candidate_fraction of the candidates survive, the RSRP threshold rises by "
        "threshold_step_db (TS 36.213 14.1.1.6 step 7; the default, the standard's); model_cbr: the analytical "
        "model's assumption (Gonzalez-Martin et al. 2019 eqs. 21-23, 34): with probability alpha(CBR) (eq. 22: 0 "
        "below 0.2, 2 CBR - 0.4 up to 0.7, 1 above), CBR the share of the UE's candidates excluded at the initial "
        "threshold, the UE keeps the initial threshold and chooses among the candidates left (Step 2 alone, however "
        "few; raised as 3gpp only where none is left), otherwise as 3gpp (Step 3); one extra draw per selection",
        choices=("3gpp", "model_cbr"),
    )
    paper_best_k: int = key_field(3, "Number of best candidates in the paper's rule", "", 1, 100)
    keep_probability: float = key_field(
        0.0, "Probability of keeping the resource when the counter expires", "", 0.0, 0.8
    )
    counter_min: int = key_field(
        5, "Reselection counter lower bound at RRI >= 100 ms (scaled by 100/RRI below)", "", 1, 100
    )
    counter_max: int = key_field(
        15, "Reselection counter upper bound at RRI >= 100 ms (scaled by 100/RRI below)", "", 1, 100
    )
    exclude_unmonitored: bool = key_field(
        True, "Exclude candidates in the subframe of the UE's own transmission (not monitored: half duplex)"
    )
    reservation_signalling: str = key_field(
        "standard",
        "standard: the keep/reselect draw happens when the counter reaches 1 and the last SCI of a UE that will "
        "reselect carries no reservation (TS 36.213 14.1.1.6, TS 36.321 5.14.1.1; the default); always: every SCI "
        "reserves its resource for the next period and the draw happens at the period end (the paper presets' "
        "simplification)",
        choices=("always", "standard"),
    )
    reselection_timing: str = key_field(
        "per_ue",
        "When counters run and reselections happen: per_ue: at each UE's own packet arrival (its generation slot "
        "n): the counter counts down there, and a reselecting UE senses the 1000 ms before n (SCIs heard earlier "
        "in the same period included) and selects in [n + T1, n + T2], from the same period on when the resource "
        "falls after n (TS 36.321 5.14.1.1, TS 36.213 14.1.1.6; the default); period_end: for every vehicle at the "
        "end of each reservation period, on the sensing map of the period just ended (the paper presets' "
        "simplification)",
        choices=("period_end", "per_ue"),
    )
    sci_decoding: str = key_field(
        "sinr",
        "Which SCIs a receiver decodes, and so which reservations its sensing excludes (TS 36.213 14.1.1.6): "
        "sinr: the standard's behaviour (the default), only a decoded PSCCH counts, decided per receiver by a "
        "draw against the PSCCH BLER at the link's SINR (same interference as the PSSCH in that subframe) plus "
        "sci_sinr_offset_db, NIST's ns-3 PSCCH curve (sim/data/nist-pscch-awgn-siso.csv; docs/model.md); always: "
        "every SCI not lost to half duplex or below radio.sensitivity_dbm (the paper presets' simplification)",
        choices=("always", "sinr"),
    )
    sci_sinr_offset_db: float = key_field(
        0.0,
        "With sci_decoding=sinr: PSCCH SINR minus the PSSCH link's SINR (power share of the 2 PSCCH RBs, "
        "receiver gain; 0: the same SINR as the PSSCH)",
        "dB",
        -20.0,
        20.0,
    )
    sci_gates_pssch: bool = key_field(
        True,
        "With sci_decoding=sinr: a receiver that misses the SCI cannot decode the PSSCH it schedules (SCI format "
        "1 carries the PSSCH's frequency resources and MCS, TS 36.212 5.4.3.1.2): a packet is received only if "
        "both decode (P = P_PSSCH x P_SCI, one draw each; the default); false: the PSSCH outcome alone, the SCI "
        "only steering the sensing (the paper presets'; must be false with sci_decoding=always)",
    )

    def _check(self) -> None:
        if self.counter_min > self.counter_max:
            raise ConfigError(
                f"sps.counter_min ({self.counter_min}) must not exceed sps.counter_max ({self.counter_max})"
            )
        if self.sci_decoding == "always" and self.sci_sinr_offset_db != 0.0:
            raise ConfigError(
                f"sps.sci_sinr_offset_db ({self.sci_sinr_offset_db:g}) applies to the PSCCH SINR of "
                "sps.sci_decoding=sinr only: set sps.sci_decoding=sinr or sps.sci_sinr_offset_db=0"
            )
        if self.sci_gates_pssch and self.sci_decoding != "sinr":
            raise ConfigError(
                "sps.sci_gates_pssch=true needs the SCI draws of sps.sci_decoding=sinr (it is "
                f"{self.sci_decoding!r}): set sps.sci_decoding=sinr or sps.sci_gates_pssch=false"
            )


#: the shipped PER curves (``link.per_curve``; package data ``cv2x_marl/sim/data/<name>.csv``,
#: read by :func:`cv2x_marl.sim.link.load_per_curve`)
PER_CURVES: tuple[str, ...] = ("r1-160284-190b-r0.5", "r1-160284-190b-r0.7")
#: ways of interpolating a PER table between its points (``link.per_interpolation``)
PER_INTERPOLATIONS: tuple[str, ...] = ("linear", "log")
#: LOS state of a moved vehicle's links in the links' ground truth (:mod:`cv2x_marl.sim.ground_truth`, the env's
#: ``truth_los``, ``cv2x-marl gbmu --truth-los``): the snapshot's, from the geometry, or always LOS
TRUTH_LOS: tuple[str, ...] = ("snapshot", "geometry", "always")


@dataclass(frozen=True)
class LinkConfig(Section):
    """SINR -> success probability abstraction (eq. 8)."""

    _name = "link"
    model: str = key_field(
        "per_table",
        "per_table: interpolated PER(SINR); rayleigh: closed form over Rayleigh fading; threshold: SINR >= theta",
        choices=("per_table", "rayleigh", "threshold"),
    )
    per_curve: str = key_field(
        "r1-160284-190b-r0.5",
        "PER curve (package data)",
        choices=PER_CURVES,
    )
    sinr_threshold_db: float = key_field(
        2.0, "Decoding threshold theta for the rayleigh and threshold models", "dB", -20.0, 40.0
    )
    inband_emission_db: float | None = key_field(
        None,
        "Leakage from transmissions on other subchannels of the same subframe, relative, with "
        "inband_emission_model=flat; null: none (must be null with inband_emission_model=3gpp)",
        "dB",
        -80.0,
        0.0,
    )
    inband_emission_model: str = key_field(
        "3gpp",
        "In-band emission from transmissions on other subchannels of the same subframe: 3gpp: the TS 36.101 "
        "6.5.2.3 in-band emission mask with TR 36.843 A.2.1.5's W, X, Y, Z as WiLabV2Xsim uses them (general, IQ "
        "image, carrier leakage; sim/inband.py, docs/model.md; the default); flat: the constant "
        "inband_emission_db (none when that is null: the paper presets')",
        choices=("flat", "3gpp"),
    )
    per_interpolation: str = key_field(
        "log",
        "How per_table interpolates the PER curve between its points: log: ln PER linear in SINR (dB), PER "
        "geometric between points, which follows the waterfall (7 dB on the r0.5 curve: 0.055 linear, 0.042 log; "
        "the default); linear: PER linear in SINR (dB) (the paper presets'). Same at the table points",
        choices=PER_INTERPOLATIONS,
    )
    interference: str = key_field(
        "sum",
        "How co-channel transmitters interfere: sum: their powers add in the SINR (eq. 8; the default); "
        "independent: the analytical model's assumption (Gonzalez-Martin et al. 2019 eq. 14): each interferer "
        "alone, P = P0 prod_i (P_i / P0) with P_i the success at the SINR of interferer i alone and P0 without "
        "interference (needs link.model=per_table, channel.fading=none, no in-band emission; runs the numpy chunk)",
        choices=("sum", "independent"),
    )
    max_range_m: float | None = key_field(
        None,
        "Interference and link cut-off: pairs farther apart are not computed; null: all pairs",
        "m",
        1.0,
        1e6,
    )
    pair_state: str = key_field(
        "auto",
        "Pair state with max_range_m set: dense: N x N shadowing and an all-pairs index; sparse: only the pairs "
        "in range (a pair's shadowing is drawn when it first comes in range and forgotten when it leaves; "
        "docs/model.md, Scale); auto: sparse from 2,500 vehicles up. Without max_range_m it is always dense",
        choices=("auto", "dense", "sparse"),
    )

    def _check(self) -> None:
        if self.interference == "independent" and (self.model != "per_table" or self.has_inband_emission):
            raise ConfigError(
                "link.interference=independent (the analytical model's interferers one at a time) needs "
                f"link.model=per_table (got {self.model}) and no in-band emission (link.inband_emission_model=flat "
                "with link.inband_emission_db null)"
            )
        if self.inband_emission_model == "3gpp" and self.inband_emission_db is not None:
            raise ConfigError(
                f"link.inband_emission_db ({self.inband_emission_db:g}) is the flat model's leakage: with "
                "link.inband_emission_model=3gpp set link.inband_emission_db to null (or use "
                "link.inband_emission_model=flat)"
            )

    @property
    def has_inband_emission(self) -> bool:
        """Whether transmissions on other subchannels of the same subframe interfere (either model)."""
        return self.inband_emission_model == "3gpp" or self.inband_emission_db is not None


@dataclass(frozen=True)
class MetricsConfig(Section):
    """What is measured and recorded."""

    _name = "metrics"
    prr_bin_m: float = key_field(10.0, "Width of the PRR-vs-distance bins", "m", 0.0, 1000.0, lo_open=True)
    max_distance_m: float = key_field(650.0, "PRR-vs-distance range (links farther are not binned)", "m", 1.0, 1e6)
    interferer_range_m: float = key_field(
        200.0, "NSV range th_I: co-channel transmitters within this distance of the receiver", "m", 1.0, 1e5
    )
    record_links: bool = key_field(True, "Keep the per-link table (stage-2 data); false saves memory on large runs")
    nsv_scope: str = key_field(
        "co_channel",
        "Which transmitters NSV counts (and the main interferer l is the nearest of): co_channel: those on the "
        "link's resource (same subframe and subchannel); concurrent: every vehicle transmitting in the same "
        "subframe (a reading of the paper's Table 3, docs/model.md). Dataset, fit, GBMU and observations follow it",
        choices=("co_channel", "concurrent"),
    )


@dataclass(frozen=True)
class SimConfig(Section):
    """Run length."""

    _name = "sim"
    n_subframes: int = key_field(
        10240, "Subframes simulated by `simulate` (paper Table 1: 10240)", "subframes", 1, 10**8
    )
    warmup_subframes: int = key_field(
        1000, "Subframes run before measuring (fills the sensing window)", "subframes", 0, 10**7
    )
    warmup_mode: str = key_field(
        "until_reselected",
        "until_reselected: warm up for warmup_subframes, then go on a period at a time until every vehicle has "
        "made a sensing-based selection (the default); fixed: warmup_subframes only (the paper presets'; vehicles "
        "whose counter has not expired are still on their random initial resource when measuring starts). The "
        "run summary reports the SPS state at the start of the measurement (sps_state_at_start)",
        choices=("fixed", "until_reselected"),
    )


#: every section by its name, in the order of :class:`~cv2x_marl.config.ScenarioConfig`
SECTIONS: dict[str, type[Section]] = {
    "road": RoadConfig,
    "vehicles": VehiclesConfig,
    "radio": RadioConfig,
    "channel": ChannelConfig,
    "traffic": TrafficConfig,
    "sps": SpsConfig,
    "link": LinkConfig,
    "metrics": MetricsConfig,
    "sim": SimConfig,
}
