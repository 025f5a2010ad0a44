"""The browser viewer's side in the core: the per-frame encoding of an avatar (:mod:`avatar.viewer.codec`, mirrored
by ``viewer/src/pose.js``) and the page's folder written from a trained avatar (:mod:`avatar.viewer.page`). The
local server that serves a run's pages is ``pipeline.view``."""
