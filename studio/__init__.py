"""Likeness Studio: pose, animate and perform a head in the browser (``likeness studio``).

A web page (viser: three.js scene and controls) on the skin predictor, with the daemon reached only through the
public protocol (:mod:`models.client`). Modules: :mod:`studio.head` (channels), :mod:`studio.skin` (strain picture),
:mod:`studio.clipdoc` and :mod:`studio.arkit_csv` (clips), :mod:`studio.daemon_client` (protocol client),
:mod:`studio.app` and its tabs (the page), :mod:`studio.frontdoor` (serving it), :mod:`studio.cli` (the command).
"""
