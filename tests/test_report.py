"""The demo's report and previews are legible: words for the statistics, scales that one outlier
does not squash, the same colours with a key for the model map in report.png and model.png,
previews at a readable size, the relit light's angle said both ways."""

import numpy as np
import torch
from PIL import Image

from torchspec.model.brdf import SVBRDF
from torchspec.report import MODEL_COLOURS, relit_title, shared_limit, stat_label, write_previews


def test_statistics_in_words():
    assert stat_label("matte_share_ks0") == "matte pixels fitted without a lobe (share)"
    assert stat_label("varnished_ks") == "varnished: k_s rel. error"
    assert stat_label("gilded_alpha2") == "gilded: 2nd lobe alpha rel. error"
    assert stat_label("something_new") == "something_new"


def test_a_shared_scale_ignores_one_outlier():
    truth = np.linspace(0.0, 0.15, 400)
    fit = truth.copy()
    fit[7] = 1.0  # one pixel's alpha at the bound
    assert shared_limit(fit, truth) < 0.16  # not 1.0: the 99th percentile of either map
    assert shared_limit(np.zeros(4)) > 0


def test_relit_title_says_the_elevation():
    assert "30 deg from it (elevation 60 deg" in relit_title(30.0)


def test_previews_are_readable_with_a_model_key(tmp_path):
    h, w = 8, 8
    normal = torch.zeros(h, w, 3, dtype=torch.float64)
    normal[..., 2] = 1
    maps = SVBRDF(normal, torch.full((h, w, 3), 0.3), torch.full((h, w, 1), 0.2), torch.full((h, w, 2), 0.1))
    model = torch.zeros(h, w)
    model[:4] = 1  # diffuse above ward-iso
    written = write_previews(tmp_path, maps, model=model)
    for path in written:
        assert min(Image.open(path).size) >= 300, path  # was 8 x 8 pixels: one pixel per texel
    image = np.asarray(Image.open(tmp_path / "model.png").convert("RGB"))
    colours = {tuple(int(MODEL_COLOURS[i][k : k + 2], 16) for k in (1, 3, 5)) for i in (0, 1)}
    seen = {tuple(p) for p in image.reshape(-1, 3)}
    assert colours <= seen, "the model map is drawn in MODEL_COLOURS, as in report.png"
