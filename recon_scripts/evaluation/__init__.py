"""Evaluation suite (paper §5): two-view pose AUC, WxBS scores, LTLL-style registration, historical
proxy.

Modules
    metrics       pose errors, pose AUC (SuperGlue/OANet YFCC protocol), essential/fundamental
                  RANSAC, WxBS scores by hand-labelled correspondences.
    reference     reference cameras of the held-out scenes (COLMAP models, Strecha, instant-ngp).
    matcher_specs matcher variants named on the command line: a preset of matchers.PRESETS
                  (``raw_mutual``), options over it (``guided:window_cells=2``).
    ground_truth  pose errors of a reconstruction against a ground-truth model (the synthetic
                  scene's).
    two_view      the two-view protocol (pairs, SIFT, matching, pose AUC) and the WxBS protocol.
    manifest      multi-scene manifests (datasets/*.json): scan a local copy, lay scenes out, run
                  them.
    registration  registered ratio per scene (Fig. 5a) and agreement with a reference model.
    proxy         offline historical proxy: half of each set degraded, distractors from other
                  scenes.
    tables        Markdown tables and PNG plots.
"""
