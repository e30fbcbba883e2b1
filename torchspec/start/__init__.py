"""Where a fit starts: the diffuse part by robust photometric stereo
(:mod:`~torchspec.start.photometric`), then the specular peak of what it leaves
(:mod:`~torchspec.start.specular`), located by finite-rate-of-innovation sampling
(:mod:`~torchspec.start.fri`)."""
