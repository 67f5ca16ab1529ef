"""The run report's figure pieces drawn directly (tests/test_reports.py renders whole reports): an empty loss panel
says why it is empty, a camera image is shown as the camera saw it, and the class legend lists exactly the classes
that the class-id panels show (none for point clouds)."""

from __future__ import annotations

import numpy as np

from distilkit.report import plots


def test_a_loss_panel_without_a_logged_loss_says_why() -> None:
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots()
    plots.loss_curves(ax, {})
    assert [t.get_text() for t in ax.texts] == ["no loss logged: the run is shorter than train.log_every"]
    assert ax.get_legend() is None
    plt.close(fig)


def test_a_camera_input_is_shown_as_an_image_and_the_legend_lists_the_shown_classes() -> None:
    import matplotlib.pyplot as plt

    rng = np.random.default_rng(0)
    image = rng.integers(0, 256, (6, 10, 3), dtype=np.uint8)
    prediction = np.array([[0, 2], [2, 5]], dtype=np.int64)
    target = np.array([[0, 2], [7, 99]], dtype=np.int64)  # 99: no such class, not in the legend
    names = np.array([f"class{i}" for i in range(8)])
    colours = rng.integers(0, 256, (8, 3), dtype=np.uint8)
    preview = {"input": image, "prediction": prediction, "target": target, "extent": np.array([0, 51.2, -25.6, 25.6]),
               "class_names": names, "class_colours": colours}
    fig, axes = plt.subplots(1, 3)
    plots.bev_row(list(axes), preview, model_input="5 images")
    shown = axes[0].get_images()
    assert len(shown) == 1 and np.array_equal(np.asarray(shown[0].get_array()), image)  # the pixels as they are
    assert not axes[0].axison and axes[0].get_title() == "input image\n(the model reads 5 images)"
    legend = fig.legends[0]
    assert [t.get_text() for t in legend.get_texts()] == ["class0", "class2", "class5", "class7"]
    plt.close(fig)


def test_no_class_legend_where_no_panel_shows_class_ids() -> None:
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3)
    cloud = np.random.default_rng(1).normal(size=(50, 3)).astype(np.float32)  # point clouds: coloured by height
    plots.bev_row(list(axes), {"input": cloud, "prediction": cloud, "target": cloud,
                               "extent": np.array([-5.0, 5.0, -5.0, 5.0]), "class_names": np.array(["a"]),
                               "class_colours": np.zeros((1, 3), dtype=np.uint8)})
    assert fig.legends == []
    plt.close(fig)

