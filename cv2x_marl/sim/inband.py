"""The 3GPP in-band emission model: leakage between the subchannels of one subframe.

A UE transmitting on some resource blocks (RBs) of a subframe also emits into the RBs it does not
use. TS 36.101 clause 6.5.2.3 bounds this *in-band emission* (the power in a non-allocated RB
relative to the average power per allocated RB) by three components, the general requirement,
the IQ image and the carrier leakage; the 3GPP D2D/V2X evaluation methodology (TR 36.843 Annex
A.2.1.5, reused by TR 36.885) models a realistic UE as that limit lowered by the margins W, X, Y,
Z. Per victim RB, in dB relative to the interferer's power per allocated RB:

* general: ``max(-25 - 10 log10(N_RB / L_CRB) - X,
  20 log10(EVM) - 3 - 5 (|Delta_RB| - 1) / L_CRB - W,
  -57 dBm/180 kHz - P_RB - X)``, with ``N_RB`` the RBs of the channel, ``L_CRB`` the interferer's
  allocated RBs, ``Delta_RB`` the RB offset from the edge of its allocation (1: the adjacent RB),
  ``EVM`` the error vector magnitude requirement of its modulation (TS 36.101 clause 6.5.2.1:
  17.5 % for QPSK, 12.5 % for 16QAM) and ``P_RB`` its transmitted power per allocated RB (dBm);
* IQ image: ``-25 - Y`` in the RBs mirroring the allocation about the carrier (RB ``r`` mirrors
  ``N_RB - 1 - r``);
* carrier leakage: ``-25 - Z`` in the RB(s) at the carrier (DC): the middle RB for an odd
  ``N_RB``, the two middle RBs for an even one;

the three added in linear units, with ``{W, X, Y, Z} = {3, 6, 3, 3}`` dB.

Source. The formula and the parameter values are those of ``IBEcalculation.m`` in WiLabV2Xsim
(github.com/V2Xgithub/WiLabV2Xsim, ``MatFilesUtilityLTE/IBEcalculation.m``, commit 1b76966; the
same function in its predecessor LTEV2Vsim), whose header says it follows "the model reported in
3GPP TS 36.101 V15.0.0". We could not read TS 36.101 Table 6.5.2.3.1-1 nor TR 36.843 Table
A.2.1.5-1 themselves (no citable copy was at hand), so the placement of W and X within the
general term is WiLabV2Xsim's. Two deliberate differences from that code:

* the third general term is the standard's ``-57 - P_RB - X`` with ``P_RB`` the interferer's power
  per allocated RB (23 dBm over 10 RB: 13 dBm, so -76 dB, never binding); WiLabV2Xsim evaluates
  ``(-57/180e3 - 0 - X) - 30``, about -36.0 dB, which binds beyond ``Delta_RB`` = 30 in a 50-RB
  channel, 2 dB above the first term's -38.0 dB there;
* the carrier-leakage RBs of an even ``N_RB`` are the two next to the carrier, 0-based
  ``N_RB/2 - 1`` and ``N_RB/2``; WiLabV2Xsim's 1-based ``ceil(N_RB/2) - 1`` and ``ceil(N_RB/2)`` are
  one RB lower.

Pool layout. Subchannel ``k`` of the pool occupies RBs ``[first_rb + k S, first_rb + (k + 1) S)``
of an ``N_RB``-RB channel, ``S`` = ``sps.subchannel_rbs``; by default the pool fills the channel
(``N_RB = n_subchannels x S``: 50 RB, 10 MHz, on the highway preset) and every transmission uses
its whole subchannel (``L_CRB = S``; PSCCH and PSSCH of one UE side by side). The leakage into a
victim subchannel is the sum over its RBs of the interferer's per-RB power times the emission,
i.e. ``sum_r 10^(E(r)/10) / L_CRB`` times the interferer's received power in its own subchannel
(the quantity the simulator computes), which with equal allocations is WiLabV2Xsim's average of
``10^(E(r)/10)`` over the victim's RBs. The simulator adds ``M[v, i]`` times the received power to
the interference of a link on ``v`` and to the S-RSSI of ``v`` (TS 36.214: the total received
power in the subchannel; WiLabV2Xsim's ``sensedPowerCV2X.m`` does the same).

Example:
    >>> m = leakage_matrix(n_subchannels=5, subchannel_rbs=10, tx_power_dbm=23.0)
    >>> round(10 * float(np.log10(m[1, 0])), 2)  # the adjacent subchannel, dB
    -23.15
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike, NDArray

if TYPE_CHECKING:
    from cv2x_marl.config import ScenarioConfig

FloatArray = NDArray[np.float64]

#: TR 36.843 A.2.1.5 margins of a realistic UE below the TS 36.101 limit, dB (as WiLabV2Xsim sets them):
#: W on the EVM term of the general part, X on its other two terms, Y on the IQ image, Z on the carrier leakage
W_DB = 3.0
X_DB = 6.0
Y_DB = 3.0
Z_DB = 3.0
#: TS 36.101 clause 6.5.2.1 EVM requirement for QPSK (the PER curves' modulation), as a fraction
EVM_QPSK = 0.175
#: the -25 dB base of the TS 36.101 general, IQ-image and carrier-leakage rows
BASE_DB = -25.0
#: the absolute floor of the general part, dBm per 180 kHz RB
FLOOR_DBM_PER_RB = -57.0

COMPONENTS = ("general", "iq_image", "carrier_leakage")


def general_emission_db(
    delta_rb: ArrayLike,
    alloc_rbs: int,
    total_rbs: int,
    p_rb_dbm: float,
    evm: float = EVM_QPSK,
    w_db: float = W_DB,
    x_db: float = X_DB,
) -> FloatArray:
    """General in-band emission (TS 36.101 clause 6.5.2.3, general row) lowered by TR 36.843's W, X.

    Args:
        delta_rb: [...] RB offset of the victim RB from the nearest edge of the interferer's
            allocation, >= 1 (1: the adjacent RB); integer-valued.
        alloc_rbs: ``L_CRB``, the interferer's contiguous allocated RBs.
        total_rbs: ``N_RB``, the RBs of the channel.
        p_rb_dbm: ``P_RB``, the interferer's transmitted power per allocated RB, dBm.
        evm: the EVM requirement of the interferer's modulation, a fraction (QPSK: 0.175).
        w_db: margin on the EVM term, dB.
        x_db: margin on the other two terms, dB.

    Returns:
        [...] emission in dB relative to the interferer's power per allocated RB:
        ``max(-25 - 10 log10(N_RB / L_CRB) - X, 20 log10(EVM) - 3 - 5 (|Delta_RB| - 1) / L_CRB - W,
        -57 - P_RB - X)``.

    Raises:
        ValueError: an offset below 1 (an allocated RB) or an allocation not inside the channel.
    """
    d = np.asarray(delta_rb, dtype=np.float64)
    if np.any(d < 1):
        raise ValueError("delta_rb must be >= 1 (1: the RB next to the allocation)")
    if not 1 <= alloc_rbs <= total_rbs:
        raise ValueError(f"alloc_rbs must be in [1, total_rbs={total_rbs}], got {alloc_rbs}")
    flat = BASE_DB - 10.0 * np.log10(total_rbs / alloc_rbs) - x_db
    evm_term = 20.0 * np.log10(evm) - 3.0 - 5.0 * (np.abs(d) - 1.0) / alloc_rbs - w_db
    floor = FLOOR_DBM_PER_RB - p_rb_dbm - x_db
    return np.asarray(np.maximum(np.maximum(flat, evm_term), floor), dtype=np.float64)


def rb_emission(
    alloc_start: int,
    alloc_rbs: int,
    total_rbs: int,
    p_rb_dbm: float,
    evm: float = EVM_QPSK,
    components: tuple[str, ...] = COMPONENTS,
) -> FloatArray:
    """Emission of one allocation into every RB of the channel, linear, relative to its power per RB.

    Args:
        alloc_start: first allocated RB (0-based).
        alloc_rbs: ``L_CRB``, contiguous allocated RBs.
        total_rbs: ``N_RB``, RBs of the channel.
        p_rb_dbm: transmitted power per allocated RB, dBm.
        evm: EVM requirement of the modulation, a fraction.
        components: which of ``general``, ``iq_image``, ``carrier_leakage`` to add.

    Returns:
        [N_RB] linear emission per RB: 1 in the allocated RBs, the sum of the chosen components
        (``10^(dB/10)``) elsewhere.
    """
    unknown = set(components) - set(COMPONENTS)
    if unknown:
        raise ValueError(f"unknown in-band emission components {sorted(unknown)}; allowed: {', '.join(COMPONENTS)}")
    if alloc_start < 0 or alloc_start + alloc_rbs > total_rbs:
        raise ValueError(f"allocation [{alloc_start}, {alloc_start + alloc_rbs}) is not inside {total_rbs} RBs")
    rb = np.arange(total_rbs)
    stop = alloc_start + alloc_rbs - 1  # last allocated RB
    inside = (rb >= alloc_start) & (rb <= stop)
    out = np.zeros(total_rbs)
    outside = ~inside
    if "general" in components:
        delta = np.maximum(alloc_start - rb, rb - stop)[outside]
        out[outside] += 10.0 ** (general_emission_db(delta, alloc_rbs, total_rbs, p_rb_dbm, evm) / 10.0)
    if "iq_image" in components:
        image = total_rbs - 1 - rb
        hit = outside & (image >= alloc_start) & (image <= stop)
        out[hit] += 10.0 ** ((BASE_DB - Y_DB) / 10.0)
    if "carrier_leakage" in components:
        dc = [total_rbs // 2] if total_rbs % 2 else [total_rbs // 2 - 1, total_rbs // 2]
        hit = np.zeros(total_rbs, dtype=bool)
        hit[dc] = True
        out[hit & outside] += 10.0 ** ((BASE_DB - Z_DB) / 10.0)
    out[inside] = 1.0
    return out


def leakage_matrix(
    n_subchannels: int,
    subchannel_rbs: int,
    tx_power_dbm: float,
    total_rbs: int | None = None,
    first_rb: int = 0,
    evm: float = EVM_QPSK,
    components: tuple[str, ...] = COMPONENTS,
) -> FloatArray:
    """Relative leakage between the subchannels of one subframe of the pool.

    Args:
        n_subchannels: subchannels of the pool (``sps.n_subchannels``).
        subchannel_rbs: RBs per subchannel (``sps.subchannel_rbs``); each transmission uses one
            whole subchannel.
        tx_power_dbm: transmit power of every UE (``radio.tx_power_dbm``); sets ``P_RB``.
        total_rbs: ``N_RB`` of the channel; None: the pool fills it (``n_subchannels x subchannel_rbs``).
        first_rb: first RB of the pool in the channel (0-based).
        evm: EVM requirement of the modulation (QPSK: 0.175).
        components: which emission components to include (all three by default).

    Returns:
        [n_sub, n_sub] ``M[v, i]``: power leaking from a transmission on subchannel ``i`` into the
        RBs of subchannel ``v``, as a fraction of that transmission's power in its own subchannel
        (``sum_{r in v} e_i(r) / subchannel_rbs``); 1 on the diagonal (co-channel). A receiver's
        interference on subchannel ``v`` is ``sum_i M[v, i] x`` (power received from the
        transmitters on subchannel ``i``).
    """
    n_rb = n_subchannels * subchannel_rbs if total_rbs is None else total_rbs
    if first_rb < 0 or first_rb + n_subchannels * subchannel_rbs > n_rb:
        raise ValueError(
            f"a pool of {n_subchannels} x {subchannel_rbs} RBs from RB {first_rb} does not fit in {n_rb} RBs"
        )
    p_rb_dbm = tx_power_dbm - 10.0 * np.log10(subchannel_rbs)
    out = np.empty((n_subchannels, n_subchannels))
    for i in range(n_subchannels):  # interferer; n_subchannels <= 50
        e = rb_emission(first_rb + i * subchannel_rbs, subchannel_rbs, n_rb, p_rb_dbm, evm, components)
        per_sub = e[first_rb : first_rb + n_subchannels * subchannel_rbs].reshape(n_subchannels, subchannel_rbs)
        out[:, i] = per_sub.sum(axis=1) / subchannel_rbs
    return out


def pool_leakage_matrix(config: ScenarioConfig) -> FloatArray:
    """:func:`leakage_matrix` of a scenario's pool (``sps.n_subchannels`` x ``sps.subchannel_rbs``,
    filling the channel; ``radio.tx_power_dbm``); [n_sub, n_sub], 1 on the diagonal."""
    return leakage_matrix(config.sps.n_subchannels, config.sps.subchannel_rbs, config.radio.tx_power_dbm)


def pool_leakage_weights(config: ScenarioConfig) -> FloatArray | None:
    """The interference weights between *different* subchannels that ``link.inband_emission_model``
    and ``link.inband_emission_db`` give; None when nothing leaks.

    Returns:
        [n_sub, n_sub] ``W[v, i]`` with a zero diagonal: ``3gpp`` the :func:`pool_leakage_matrix`,
        ``flat`` the constant ``10^(inband_emission_db / 10)`` off the diagonal; None for ``flat``
        with ``inband_emission_db`` null.
    """
    link = config.link
    n_sub = config.sps.n_subchannels
    if link.inband_emission_model == "3gpp":
        w = pool_leakage_matrix(config)
    elif link.inband_emission_db is not None:
        w = np.full((n_sub, n_sub), 10.0 ** (link.inband_emission_db / 10.0))
    else:
        return None
    np.fill_diagonal(w, 0.0)
    return w
