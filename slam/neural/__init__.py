"""The neural allocentric spatial memory of thesis chapter 4 (MapNet-style localisation, LSTM memory,
recall by geometric culling + decoding, hallucination of unseen regions), in PyTorch."""

POSE_SCORES = ("overlap", "sum")
"""How the localisation scores a pose against the memory (:meth:`slam.neural.model.NeuralMemory.forward`'s
``score``); here, free of torch, so that the ``neural`` backend's configuration can check it before loading a model."""
