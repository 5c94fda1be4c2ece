"""layerwatch.geometry: calibrate the camera once, then warp every layer's photo into the top view.

Modules (each imports OpenCV lazily where it can):

- :mod:`.camera`      ``CameraModel`` (K, distortion, pose, save/load, ``scaled_to``)
- :mod:`.topview`     ``TopView`` (px/mm, observed square, ``top_from_bed``)
- :mod:`.calibration` ``calibrate_intrinsics(photos, BoardSpec)``, ``approximate_intrinsics(size, hfov_deg)``
- :mod:`.markers`     ``detect_dots(photo)``, ``detect_aruco(photo, dictionary)``
- :mod:`.pose`        ``solve_pose``, ``locate_bed(camera, photo, markers, topview)``, ``camera_moved``
- :mod:`.homography`  ``top_from_image(camera, topview, z)`` (paper eqs. 1-3)
- :mod:`.warp`        ``TopViewWarper(camera, topview).warp(photo, z) -> (top, valid)``, ``occlusion_hint``
- :mod:`.synthetic`   ``render_bed_scene``, ``project_points`` (ground-truth photos)
- :mod:`.stack`       ``layer_stack(tops)``, ``layer_array(tops)`` (paper Fig. 7)
"""
