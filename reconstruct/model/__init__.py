"""The CAPS observation model as a reconstruction sees it (paper sections 3.1-3.2): the raw frames
rearranged into observations (:mod:`.rearrange`), the array's geometry and PSF (:mod:`.observation_model`),
the confidence of each observation (CAGF, :mod:`.cagf`), the confidence-guided data term
(:mod:`.data_term`) and the fused initial estimate (:mod:`.init_fusion`)."""
