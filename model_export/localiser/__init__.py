"""The brain localiser: a 2.5D U-Net trained on synthetic whole-uterus stacks, exported to ONNX.

``scenes`` generates the training and validation stacks (atlas brains in generated surroundings),
``net`` holds the network, ``train`` trains, exports and evaluates it.
"""
