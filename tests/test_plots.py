"""Pictures a person reads: the posterior picture shows the estimate up close even when it is far from the truth."""
import cv2
import numpy as np

from satloc.evaluation.plots import plot_posterior
from satloc.geometry import Pose2
from satloc.localizers.database import Localization
from satloc.satmap import SatelliteMap


def _result(est: Pose2) -> Localization:
    rng = np.random.default_rng(0)
    cand = np.c_[rng.uniform(0, 400, 300), rng.uniform(-300, 0, 300), np.zeros(300)]
    post = rng.random(300)
    return Localization(estimate=est, candidates=cand, posterior=post / post.sum(), inlier_score=4.0, inlier=True,
                        num_samples=100)


def test_posterior_picture_adds_a_zoom_on_a_far_estimate(tmp_path):
    sm = SatelliteMap(np.full((300, 400, 3), 90, np.uint8), 1.0, (0.0, 0.0))
    truth = Pose2(100.0, -100.0, 0.0)
    near, far = tmp_path / "near.png", tmp_path / "far.png"
    assert plot_posterior(sm, _result(Pose2(110.0, -95.0, 0.0)), truth, near) == 2
    assert plot_posterior(sm, _result(Pose2(238.0, -100.0, 0.0)), truth, far) == 3   # 138 m away
    assert plot_posterior(sm, _result(Pose2(238.0, -100.0, 0.0)), None, tmp_path / "none.png") == 2
    a, b = cv2.imread(str(near)), cv2.imread(str(far))
    assert b.shape[1] > 1.3 * a.shape[1] and abs(b.shape[0] - a.shape[0]) < 0.05 * a.shape[0]   # one more panel
