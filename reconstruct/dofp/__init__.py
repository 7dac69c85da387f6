"""What the DoFP colour-polarization demosaicking family shares: the mosaic's geometry (:mod:`.mosaic`),
residual interpolation (:mod:`.residual_interpolation`, also the Bayer demosaicking of the registration
and of ``caps-naive``), Menon 2007 Bayer demosaicking (:mod:`.menon2007`, ``caps-naive``'s and ``array-kr``'s),
the two-step bilinear demosaicking (:mod:`.bilinear`, which ``cpdnet`` refines) and
the registered-method body (:mod:`.method_body`). The methods themselves
are ``reconstruct/methods/dofp_*.py`` and ``cpdnet.py``."""
