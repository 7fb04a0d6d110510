"""``usdrelight serve``: the interactive relighting web app (built on viser).

Modules: :mod:`.state` (an editable light and its UsdLux / record / widget mappings), :mod:`.files` (the
user-lights layer, uploads and exports at fixed places), :mod:`.uploads` (upload bounds, checked before
anything is buffered), :mod:`.live` (the relight loop, no GUI), :mod:`.scene_view` (3D view), :mod:`.gui`
(widgets; every client value checked), :mod:`.guard` (Host/Origin/token rules in the server's handshake),
:mod:`.app` (the server). Only :mod:`.scene_view`, :mod:`.gui`, :mod:`.guard` and :mod:`.app` need viser (the
``serve`` extra); nothing else in usdrelight imports this package.
"""
