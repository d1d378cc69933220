"""The neural allocentric spatial memory of thesis chapter 4 (MapNet-style localisation, LSTM memory,
recall by geometric culling + decoding, hallucination of unseen regions), in PyTorch.

Modules by idea: :mod:`~slam.neural.config` (the configuration tree and presets, no torch), data
(:mod:`~slam.neural.data` - the batch sources - over :mod:`~slam.neural.data2d` and :mod:`~slam.neural.data3d`),
the model (:mod:`~slam.neural.networks` - its parts -, :mod:`~slam.neural.memory` - the sequence model -,
:mod:`~slam.neural.fields`, :mod:`~slam.neural.geometry3d`, :mod:`~slam.neural.topview`),
:mod:`~slam.neural.losses`, training (:mod:`~slam.neural.train`, :mod:`~slam.neural.refine`,
:mod:`~slam.neural.refine_hallucination`), :mod:`~slam.neural.io` (save / load), :mod:`~slam.neural.inference`
(what the backend, ``slam render`` and the viewer call), evaluation (:mod:`~slam.neural.ablations`,
:mod:`~slam.neural.evaluate`, :mod:`~slam.neural.evaluate3d`, :mod:`~slam.neural.figures`) and
:mod:`~slam.neural.run` (the commands' model folders).
"""
