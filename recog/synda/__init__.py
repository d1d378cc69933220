"""SynDA (thesis chapter 5): a generator h_G that maps real-like inputs into the clean synthetic
domain the recogniser was trained on, trained only on online-augmented synthetic data.

config.py (no torch), model.py (h_G), loss.py, augment.py (the augmentation A, draw/apply),
shading.py (Blinn-Phong of Algorithm 5.1), noise.py (procedural textures), polygons.py
(occluders of Algorithm 5.2), io.py (save/load with a version + domain header), data.py (the
training views), train.py (h_G on the project's training loop), run.py (``synda train`` end to end,
the generator in front of a recogniser), inputs.py (``synda map`` inputs, ``synda augment`` samples),
evaluate.py (Tables 5.2-5.4: rows, the ablation, the object-only database of ``synda reindex``).
"""
