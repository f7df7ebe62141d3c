"""The brain localiser: a 2.5D U-Net trained on synthetic whole-uterus stacks, exported to ONNX.

``scenes`` generates the training and validation stacks (atlas brains in generated surroundings),
``net`` holds the network, ``train`` trains, exports and evaluates it.
"""

GRID_MM = 2.5
"""The network grid (mm) of the shipped localiser: shards are made on it by default, and a checkpoint
that does not record its shards' grid is exported on it (its ONNX metadata carry it to the service)."""
