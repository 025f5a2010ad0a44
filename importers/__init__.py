"""Readers of capture data from outside the project, each into the capture layout (:mod:`data_schemas.capture`):
the DECAF release, a folder of videos or images with its calibration (the project's own, COLMAP, nerfstudio), and
which source frames an import takes. The built-in synthetic generator is :mod:`avatar.synthetic`.

(Not called ``datasets``: that name is the Hugging Face library's, which many environments of this field have.)"""
