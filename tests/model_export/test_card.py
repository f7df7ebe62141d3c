"""The model card, on synthetic calibration numbers (no training)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from model_export.card import write_card


def _card(tmp_path: Path, calibration: dict, train_config: dict) -> str:
    info = dict(name="default", version="1.0.0", backbone="compact", label_type="anchor", input_size="96",
                pixel_spacing_mm="1.25", intensity="0-255", atlas_id="atlas", variance_threshold="8.4", commit="abc")
    config = {**dict(width=1.0, hidden=128, dropout=0.25, lr=1e-3, lr_gamma=0.2, lr_milestones=[0.6, 0.85], batch=64,
                     val_volumes=["STA24"], spatial_grid=3, grid_channels=32), **train_config}
    evaluation = dict(ed_mean_mm=40.0, ed_median_mm=38.0, ed_p90_mm=70.0, gd_mean=10.0, outlier_fraction=0.03,
                      auroc_variance_error_gt_10mm=0.6, accepted_fraction=0.4, ed_accepted_mean_mm=35.0)
    summary = dict(train_seconds=3600.0, samples_seen=500000, steps=8500, train_volumes_text="23 volumes")
    out = write_card(tmp_path / "card.md", info=info, train_summary=summary, train_config=config,
                     calibration=calibration, evaluation=evaluation, comparison=None, report_path="r.md",
                     onnx_bytes=3_000_000)
    return out.read_text()


def test_card_states_the_head_the_criterion_and_a_second_stage(tmp_path: Path) -> None:
    cal = dict(threshold=8.43, auroc=0.85, error_mm=10.0, criterion_mm=37.5, auroc_criterion=0.66, n_slices=600,
               bad_fraction=0.99, accepted_fraction=0.4, ed_accepted_mean_mm=30.0, ed_rejected_mean_mm=45.0,
               spearman_variance_error=0.35, variance=[1.0], ed_mm=[2.0])
    prior = dict(init_from=dict(checkpoint="a.pt", steps=4400, samples_seen=281554, train_seconds=1631.0,
                                val_ed_mm=43.2))
    text = _card(tmp_path, cal, prior)
    assert "1x1 convolution to 32 channels, then a 3x3 spatial grid" in text
    assert "median error, 37.5 mm" in text and "**8.43**" in text and "0.660" in text
    assert "second stage" in text and "4400 steps" in text and "**1.00 h**" in text
    plain = _card(tmp_path, {**cal, "criterion_mm": 10.0, "bad_fraction": 0.5}, {})
    assert "median error" not in plain and "second stage" not in plain and "E.D. > 10.0 mm" in plain


def test_card_of_a_distilled_trunk_states_its_teacher_and_its_schedule(tmp_path: Path) -> None:
    cal = dict(threshold=8.43, auroc=0.85, error_mm=10.0, criterion_mm=10.0, n_slices=600, bad_fraction=0.5,
               accepted_fraction=0.4, ed_accepted_mean_mm=30.0, ed_rejected_mean_mm=45.0,
               spearman_variance_error=0.35, variance=[1.0], ed_mm=[2.0])
    distilled = dict(init_from=dict(checkpoint="service/models/default/checkpoint.pt", distil="0.75"),
                     distil=dict(lr=0.002, warmup_steps=200, minutes=8.0))
    text = _card(tmp_path, cal, {**distilled, "width": 0.75})
    assert "distilled from `service/models/default/checkpoint.pt` (width 0.75" in text
    assert "lr 0.002, 200 warm-up steps then a cosine over 8.0 min (8500 steps)" in text
    assert "step decay" not in text and "second stage" not in text


def test_card_gives_both_errors_and_the_totals_per_hardware(tmp_path: Path) -> None:
    from model_export.training_record import totals

    cal = dict(threshold=3.0, auroc=0.8, error_mm=10.0, criterion_mm=10.0, auroc_criterion=0.8, n_slices=600,
               bad_fraction=0.5, accepted_fraction=0.5, ed_accepted_mean_mm=8.0, ed_rejected_mean_mm=20.0,
               spearman_variance_error=0.5, errors="twin-min")
    history = [{"hardware": "CPU, 2 cores", "samples": 400000, "seconds": 3600.0},
               {"hardware": "NVIDIA H100", "samples": 2000000, "seconds": 1200.0}]
    info = dict(name="default", version="2.0.0", backbone="compact", label_type="grid", input_size="96",
                pixel_spacing_mm="1.25", intensity="0-255", atlas_id="atlas", variance_threshold="3.0", commit="abc")
    config = dict(width=1.0, hidden=128, dropout=0.25, lr=5e-4, lr_gamma=0.2, lr_milestones=[], batch=64,
                  val_volumes=["STA24"], spatial_grid=3, grid_channels=32, loss="min")
    evaluation = dict(ed_mean_mm=30.0, ed_median_mm=28.0, ed_p90_mm=60.0, ed_under_10mm=0.1, ed_twin_mean_mm=9.5,
                      ed_twin_median_mm=7.0, ed_twin_p90_mm=18.0, ed_twin_under_10mm=0.6, on_twin_fraction=0.5,
                      gd_mean=5.0, outlier_fraction=0.03, auroc_variance_error_gt_10mm=0.8, accepted_fraction=0.5,
                      ed_accepted_mean_mm=25.0)
    summary = dict(train_seconds=4800.0, samples_seen=2400000, steps=100, totals=totals(history))
    text = write_card(tmp_path / "card.md", info=info, train_summary=summary, train_config=config, calibration=cal,
                      evaluation=evaluation, comparison=None, report_path="r.md", onnx_bytes=3_000_000).read_text()
    assert "twin-min E.D. (nearer of truth and twin) | **9.50 mm**" in text and "**30.00 mm**" in text
    assert "**2,400,000 samples**, **1.33 h**" in text
    assert "| NVIDIA H100 | 2,000,000 | 0.33 |" in text and "| CPU, 2 cores | 400,000 | 1.00 |" in text
    assert "grid of 8 x 8" in text and "nearer of the label and its left-right twin" in text
    assert "twin-min E.D. > 10 mm" in text


def test_grid_mc_samples_split_between_twins_are_put_on_one_branch() -> None:
    """A slice whose grid-label samples split 70/30 between the twins: the service's statistics (used by
    calibration and evaluation) put them on the majority branch, with a small variance and the split reported."""
    from service.geometry import encodings, iterators, se3
    from service.geometry.twin import twin, twin_label
    from service.inference.estimator import statistics

    poses = iterators.random_poses(4, np.random.default_rng(5), tz_max_mm=10.0, centre=np.array([25.0, 0.0, 0.0]))
    truth = encodings.encode("grid", poses)                                   # [4, 192]
    rng = np.random.default_rng(6)
    samples = truth[:, None] + rng.normal(scale=1.0, size=(4, 50, 192))
    other = rng.random((4, 50)) < 0.3
    samples = np.where(other[..., None], twin_label("grid", samples, 0.0), samples)
    est = statistics(samples, "grid", 0.0)
    assert np.allclose(est.twin_mass, np.minimum(other.mean(1), 1 - other.mean(1)))
    assert est.variance.max() < 5.0
    majority = np.where((other.mean(1) > 0.5)[:, None, None], twin(poses, 0.0), poses)
    assert se3.geodesic_distance(est.mean, majority).max() < 1.0
    _, naive = se3.frechet_mean_and_variance(encodings.decode("grid", samples))
    assert naive.min() > 100.0                                                # what a twin-blind mean reports


def test_card_states_its_budget_first_and_a_quick_look_below_a_served_models_scale(tmp_path: Path) -> None:
    cal = dict(threshold=3.0, auroc=0.8, error_mm=10.0, criterion_mm=10.0, auroc_criterion=0.8, n_slices=14,
               bad_fraction=0.5, accepted_fraction=0.5, ed_accepted_mean_mm=8.0, ed_rejected_mean_mm=20.0,
               spearman_variance_error=0.5, measured_on="model.onnx")
    info = dict(name="default", version="2.0.0", backbone="compact", label_type="anchor", input_size="96",
                pixel_spacing_mm="1.25", intensity="0-255", atlas_id="atlas", variance_threshold="3.0", commit="abc")
    config = dict(width=1.0, hidden=128, dropout=0.25, lr=5e-4, lr_gamma=0.2, lr_milestones=[], batch=16,
                  val_volumes=["STA24"], spatial_grid=3, grid_channels=32)
    evaluation = dict(ed_mean_mm=30.0, ed_median_mm=28.0, ed_p90_mm=60.0, gd_mean=5.0, outlier_fraction=0.03,
                      auroc_variance_error_gt_10mm=0.8, accepted_fraction=0.5, ed_accepted_mean_mm=25.0)

    def card(samples: int, budget: list) -> str:
        summary = dict(train_seconds=36.0, samples_seen=samples, steps=4)
        return write_card(tmp_path / "card.md", info=info, train_summary=summary, train_config=config,
                          calibration=cal, evaluation=evaluation, comparison=None, report_path="r.md",
                          onnx_bytes=3_000_000, budget=budget).read_text()

    quick = card(64, [("validation slices per volume of the evaluation", 7, 100)])
    head = quick.split("| | |")[0]                                    # before the card's table: up front
    assert "**Budget**: training 4 steps of batch 16 in its last stage, 64 samples in 0.01 h" in head
    assert "7 validation slices per volume of the evaluation (default 100)" in head
    assert "**Quick look**" in head and "training under 1,000,000 samples" in head
    assert "the validation slices per volume of the evaluation under its default" in head
    assert "measured on\n`model.onnx`, the file served" in quick
    served = card(6_448_616, [("validation slices per volume of the evaluation", None, 100)])
    assert "6,448,616 samples" in served and "100 validation slices per volume" in served
    assert "Quick look" not in served


def test_card_gives_the_commits_of_training_and_export_dirty_or_not(tmp_path: Path) -> None:
    cal = dict(threshold=8.43, auroc=0.85, error_mm=10.0, criterion_mm=10.0, n_slices=600, bad_fraction=0.5,
               accepted_fraction=0.4, ed_accepted_mean_mm=30.0, ed_rejected_mean_mm=45.0,
               spearman_variance_error=0.35, variance=[1.0], ed_mm=[2.0])
    summary = dict(train_seconds=3600.0, samples_seen=10, steps=1,
                   history=[{"hardware": "CPU", "samples": 10, "seconds": 3600.0, "commits": ["1234567-dirty"]}],
                   totals={"samples": 10, "hours": 1.0, "by_hardware": {"CPU": {"samples": 10, "hours": 1.0}}})
    info = dict(name="default", version="1.0.0", backbone="compact", label_type="anchor", input_size="96",
                pixel_spacing_mm="1.25", intensity="0-255", atlas_id="atlas", variance_threshold="8.4", commit="abcdef0")
    config = dict(width=1.0, hidden=128, dropout=0.25, lr=1e-3, lr_gamma=0.2, lr_milestones=[0.6, 0.85], batch=64,
                  val_volumes=["STA24"], spatial_grid=3, grid_channels=32)
    evaluation = dict(ed_mean_mm=40.0, ed_median_mm=38.0, ed_p90_mm=70.0, gd_mean=10.0, outlier_fraction=0.03,
                      auroc_variance_error_gt_10mm=0.6, accepted_fraction=0.4, ed_accepted_mean_mm=35.0)
    text = write_card(tmp_path / "card.md", info=info, train_summary=summary, train_config=config, calibration=cal,
                      evaluation=evaluation, comparison=None, report_path="r.md", onnx_bytes=1).read_text()
    assert ("| commit | abcdef0 at export; training at 1234567-dirty (-dirty: with uncommitted changes to tracked "
            "files) |") in text
