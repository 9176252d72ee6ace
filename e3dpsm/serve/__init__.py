"""`e3dpsm serve`: a live pose viewer over WebSockets (aiohttp).

protocol.py  the message types both ways, built and validated in one place (docs/serve.md)
clients.py   per-client bounded send queues, so a slow client never slows anyone else
source.py    replay of a recording at its own pace, or a live `dv://` source
estimator.py the estimation loop: onnxruntime steps off the event loop, poses broadcast
security.py  who may reach the viewer: token and cookie, Host and Origin checks, headers, rate limit
app.py       the aiohttp application: page, socket, the security rules applied
report.py    serve.report.json
static/      the page (plain JS + canvas, no CDN)

Torch-free like the streaming runtime it drives.
"""
