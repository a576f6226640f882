"""experiments.paper_800px: its scene is NeRF Synthetic sized and its table reads a run's results."""

from __future__ import annotations

from experiments import paper_800px as P


def test_the_scene_has_a_nerf_synthetic_scenes_views():
    p = P.preset()
    assert (p.resolution, p.train_views, p.test_views, p.surface_samples) == (800, 100, 200, 300_000)


def test_the_table_states_the_projection_and_the_memory_goal():
    epoch = {"epoch": 1, "steps": 5, "train_s": 20.0, "psnr_train": 12.0, "alive": 1000, "round_s": None,
             "compiles": 1}
    paper = {"config_key": "k", "epochs_planned": 4, "steps_per_epoch": 5, "batch_rays": 4096, "stopped": None,
             "load_images_s": 1.0, "initial_cloud": {"points": 1000, "source": "carving", "seconds": 2.0},
             "wall_s": 30.0, "calls": [{"epoch": 1, "host_peak_rss_bytes": 3 * 2**30}, {"epoch": 2}],
             "epochs": [epoch, {**epoch, "epoch": 2, "round_s": 9.0, "compiles": 0}],
             "s_per_step": 4.0, "train_rays_per_s": 1024,
             "test": {"views": 2, "image_px": 800, "psnr": 20.0, "view_s": [60.0, 30.0], "s_per_view": 30.0,
                      "lost_segments": 0},
             "projected": {"steps": 80000, "train_s": 320000, "rounds": 9, "rounds_s": 81, "initial_cloud_s": 2.0,
                           "test_views": 200, "eval_s": 6000, "total_h": 90.6},
             "memory": {"host_peak_rss_bytes": 20 * 2**30, "device_peak_bytes": None}}
    md = P.markdown({"device": {"kind": "cpu"}, "commit": "abc", "command": "python -m experiments.paper_800px",
                     "paper": paper})
    assert "**90.6 h**" in md and "20.0 GiB" in md and "NOT met" in md
    assert "| 1 | 5 | 20.0 | 12.00 | 1000 |  | 1 | 3.0 |" in md and "| 2 | 5 | 20.0 | 12.00 | 1000 | 9.0 | 0 |  |" in md
