"""The priors (regularizers) of the reconstruction: NLSTR, the paper's nonlocal sparse tensor prior
(section 3.3, :mod:`.nlstr`, its parameters :mod:`.nlstr_parameters`, :mod:`.nlstr_blocks`, :mod:`.nlstr_prior`), Tikhonov (:mod:`.tikhonov`),
and sparse coding over a learned dictionary (:mod:`.sparse_coding`, used by ``dofp-jcpd``)."""
