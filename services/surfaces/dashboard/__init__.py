"""The coaches' browser dashboard (``msk dashboard``) and the after-session report (``msk report``).

- :mod:`services.surfaces.dashboard.bodymap`: front/back body-map SVG generated from a model pack's muscle groups.
- :mod:`services.surfaces.dashboard.bridge`: Zenoh subscriber keeping the newest frame per topic (drops stale, never queues).
- :mod:`services.surfaces.dashboard.app`: the Starlette app (page, static files, WebSocket) served by uvicorn.
- :mod:`services.surfaces.dashboard.report`: the HTML session report from an MCAP recording (matplotlib plots).
"""
