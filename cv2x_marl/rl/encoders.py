"""The neighbour encoders' former home: :mod:`cv2x_marl.policies.encoders` (moved so that the policies layer,
which loads saved models, does not reach up into the RL layer). SB3 models saved before the move name
``cv2x_marl.rl.encoders.NeighbourEncoder`` in their pickled policy settings: this alias keeps them loadable."""

from cv2x_marl.policies.encoders import (  # noqa: F401 - re-exported
    NeighbourEncoder,
    encoder_policy_kwargs,
    layout_spec,
    split_indices,
)
