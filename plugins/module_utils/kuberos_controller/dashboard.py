"""The controller's live dashboard and ``/metrics``: a small aiohttp server in a thread of the controller process.

Read-only. Every replica serves it from its own watch cache (the leader's and a standby's pages are the
same). A view is rebuilt when a watched object changes (checked every ``refresh_s``, at most once per build
time), and open pages hear of it over Server-Sent Events (``/api/stream``) and fetch the part they show: a
change reaches the page within about a second, without reloading.

Routes (docs/dashboard.md): ``/`` the page; ``/api/summary``, ``/api/resources``, ``/api/modules``,
``/api/fleets``, ``/api/software``, ``/api/events`` (JSON; filters and paging as query parameters),
``/api/placement.svg`` (the placement map of one deployment, live), ``/api/stream`` (SSE), ``/metrics``
(Prometheus), ``/healthz``; ``/login`` and ``/logout`` when tokens are checked (``auth.py``).

On 127.0.0.1 (the local default) it needs no login. Anywhere else it requires ``KubernetesAuth``: the
command line refuses to serve a non-loopback address without it. With an ``ssl.SSLContext`` it serves HTTPS.

Without a login it answers only requests whose ``Host`` header is its own loopback address and port
(``127.0.0.1:PORT``, ``localhost:PORT``, ``[::1]:PORT``); any other gets 421 and a short text. A web page open in
the developer's browser can make its own name resolve to 127.0.0.1 (DNS rebinding), but its requests still carry its
own name as ``Host``, so it cannot read the dashboard or ``/api/logs``. With a login (in a cluster, behind a Service,
a port-forward or an ingress, under any name) every request needs a token instead, which such a page does not have.
"""

from __future__ import annotations

import asyncio
import json
import logging
import threading
import time

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import labels as node_labels
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import pool as robot_pool
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.errors import KuberosError
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.placement_map import render_placement_svg
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.record import CATALOG_LABEL, STATUS_LABEL, parse_record
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_controller import dashboard_page
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_controller.auth import (
    COOKIE,
    DASHBOARD_PATH,
    METRICS_PATH,
    KubernetesAuth,
)
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_controller.certificates import ApiServerCertificate
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_controller.dashboard_logs import (
    DASHBOARD_LINES,
    instance_log,
)
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_controller.metrics import ControllerMetrics
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_controller.views import (
    Snapshot,
    View,
    build_view,
    live_placement,
    page,
    select,
)
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_controller.watch import Store, store_key

EVENT_SOURCE = "kuberos-controller"
MAX_STREAMS = 64
MAP_ROBOTS = 12  # robots on one placement map unless the page asks for others
LOOPBACK_NAMES = ("127.0.0.1", "localhost", "[::1]")  # the Host names the dashboard without a login answers to
log = logging.getLogger("kuberos.controller")

# What each list view filters on: exact-match query keys and the fields the search box looks in.
LISTS = {
    "resources": (
        ("tier", "fleet", "ready", "arch"),
        ("name", "node", "robot", "fleet", "arch", "group", "devices", "condition"),
    ),
    "modules": (
        ("namespace", "deployment", "fleet", "tier", "phase", "module", "robot", "node", "over_latency"),
        ("robot", "module", "node", "instance", "deployment", "version", "reason", "note", "phase"),
    ),
    "events": (("kind", "namespace", "warning"), ("object", "message", "reason", "namespace")),
}
FACETS = {
    "resources": ("tier", "fleet", "ready"),
    "modules": ("deployment", "fleet", "tier", "phase", "module"),
    "events": ("kind",),
}


class Dashboard:
    def __init__(self, controller, host: str = "127.0.0.1", port: int = 8611, auth: KubernetesAuth | None = None,
                 refresh_s: float = 0.2, watch_extra: bool = True, tls=None):  # fmt: skip
        self.controller = controller
        self.host = host
        self.port = port
        self.auth = auth
        self.tls = tls  # an ssl.SSLContext: HTTPS (the cookie is then Secure)
        self.refresh_s = refresh_s
        self.view = View()
        self.signature: tuple = ()
        self.build_s = 0.0
        self.building = threading.Lock()  # one build at a time (a request and the stream's loop may both ask)
        self.parsed: dict[tuple[str, str], tuple[str, object, str]] = {}
        self.node_ready: dict[str, bool] = {}
        self.node_log: list[dict] = []
        certificate = ApiServerCertificate(getattr(controller, "api_client", None))  # its remaining lifetime
        self.metrics = ControllerMetrics(self.current_view, self.leader, certificate)
        controller.metrics = self.metrics
        quiet = threading.Event()  # these stores never wake the controller's passes
        self.extra: tuple[Store, ...] = ()
        if watch_extra:
            configmaps, events = controller.kube.list_call("ConfigMap"), controller.kube.list_call("Event")
            self.extra = (
                Store("statuses", configmaps, quiet, label_selector=f"{STATUS_LABEL}=true"),
                Store("catalogs", configmaps, quiet, label_selector=f"{CATALOG_LABEL}=true"),
                Store("events", events, quiet, field_selector=f"source={EVENT_SOURCE}"),
                Store("reservations", configmaps, quiet, label_selector=f"{robot_pool.LABEL}=true"),
                Store("graphs", configmaps, quiet, label_selector=f"{node_labels.GRAPH}=true"),
            )
        self.loop: asyncio.AbstractEventLoop | None = None
        self.thread: threading.Thread | None = None
        self.started = threading.Event()
        self.error: BaseException | None = None
        self.changed_async: asyncio.Event | None = None
        self.streams = 0
        self.runner = None
        self.warned: set[str] = set()  # the view's warnings already logged (each once, not at every rebuild)

    # -- the view -------------------------------------------------------------------------------
    def current_view(self) -> View:
        return self.view

    def leader(self) -> tuple[str, bool]:
        return self.controller.identity, bool(self.controller.leading)

    def _signature(self) -> tuple:
        c = self.controller
        return (*(s.generation for s in (*c.stores, *self.extra)), c.passes, c.moves, bool(c.leading), self._holder())

    def _holder(self) -> str:
        elector = self.controller.elector
        if elector is None:
            return self.controller.identity if self.controller.leading else ""
        return getattr(elector, "holder", "") or ""

    def _records(self) -> list[tuple[dict, object, str]]:
        found = []
        seen = set()
        for configmap in self.controller.records.snapshot():
            key = store_key(configmap)
            seen.add(key)
            version = configmap["metadata"].get("resourceVersion", "")
            cached = self.parsed.get(key)
            if not cached or cached[0] != version:
                try:
                    cached = (version, parse_record(configmap), "")
                except KuberosError as exc:
                    cached = (version, None, str(exc))
                self.parsed[key] = cached
            found.append((configmap, cached[1], cached[2]))
        for key in [k for k in self.parsed if k not in seen]:
            del self.parsed[key]
        return found

    def _note_nodes(self, nodes: list[dict]) -> None:
        """Ready transitions seen since the last build, for the timeline."""
        for node in nodes:
            meta = node["metadata"]
            name = (meta.get("labels") or {}).get(node_labels.HOSTNAME, meta["name"])
            ready = next((c for c in node.get("status", {}).get("conditions") or [] if c.get("type") == "Ready"), {})
            ok = ready.get("status") == "True"
            before = self.node_ready.get(name)
            self.node_ready[name] = ok
            if before is None or before == ok:
                continue
            self.node_log.append(
                {
                    "at": ready.get("lastTransitionTime") or time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
                    "kind": "node",
                    "reason": "NodeReady" if ok else "NodeNotReady",
                    "namespace": "",
                    "object": name,
                    "message": f"node {name} is " + ("Ready again" if ok else f"NotReady ({ready.get('reason', 'no reason')})"),
                    "warning": not ok,
                    "count": 1,
                }
            )
        del self.node_log[:-200]

    def build(self, signature: tuple) -> View:
        c = self.controller
        nodes = c.nodes.snapshot()
        self._note_nodes(nodes)
        snapshot = Snapshot(
            nodes=nodes,
            pods=c.pods.snapshot(),
            records=self._records(),
            statuses=self.extra[0].snapshot() if self.extra else [],
            catalogs=self.extra[1].snapshot() if self.extra else [],
            events=self.extra[2].snapshot() if self.extra else [],
            reservations=self.extra[3].snapshot() if self.extra else [],
            graphs=self.extra[4].snapshot() if self.extra else [],
            node_log=list(self.node_log),
            leader=self._holder(),
            controller={"identity": c.identity, "leading": bool(c.leading), "passes": c.passes, "moves": c.moves},
        )
        return build_view(snapshot, generation=self.view.generation + 1, built_at=time.time())

    def refresh(self) -> bool:
        """Rebuild the view if anything it shows changed; True if it did (tests call it directly)."""
        with self.building:
            signature = self._signature()
            if signature == self.signature:
                return False
            started = time.monotonic()
            view = self.build(signature)
            self.build_s = time.monotonic() - started
            self.view, self.signature = view, signature
            for warning in view.summary.get("unreadable_reservations", ()):
                if warning not in self.warned:
                    log.warning("dashboard: %s", warning)
            self.warned = set(view.summary.get("unreadable_reservations", ()))
            return True

    # -- serving --------------------------------------------------------------------------------
    def start(self, timeout: float = 10.0) -> None:
        stop = self.controller.stop_event
        for store in self.extra:
            threading.Thread(target=store.run, args=(stop,), name=f"dashboard-{store.name}", daemon=True).start()
        self.thread = threading.Thread(target=self._serve, name="dashboard", daemon=True)
        self.thread.start()
        if not self.started.wait(timeout):
            raise RuntimeError("the dashboard did not start")
        if self.error is not None:
            raise self.error

    def stop(self) -> None:
        if self.loop is not None and self.loop.is_running():
            self.loop.call_soon_threadsafe(self.loop.stop)
        if self.thread is not None:
            self.thread.join(timeout=5)

    def _serve(self) -> None:
        from aiohttp import web

        self.loop = asyncio.new_event_loop()
        asyncio.set_event_loop(self.loop)
        try:
            self.changed_async = asyncio.Event()
            self.runner = web.AppRunner(self.app(), access_log=None, handle_signals=False, shutdown_timeout=1.0)
            self.loop.run_until_complete(self.runner.setup())
            site = web.TCPSite(self.runner, self.host, self.port, ssl_context=self.tls)
            self.loop.run_until_complete(site.start())
            if self.port == 0:
                self.port = site._server.sockets[0].getsockname()[1]  # pylint: disable=protected-access
            self.loop.create_task(self._follow())
        except BaseException as exc:
            self.error = exc
            self.started.set()
            return
        self.started.set()
        try:
            self.loop.run_forever()
        finally:
            pending = asyncio.all_tasks(self.loop)  # the follow loop, open streams: ended, not left pending
            for task in pending:
                task.cancel()
            self.loop.run_until_complete(asyncio.gather(*pending, return_exceptions=True))
            self.loop.run_until_complete(self.runner.cleanup())
            self.loop.close()

    async def _fresh(self) -> None:
        """Rebuild the view off the event loop if anything changed, and wake the open streams. Nothing is built while
        nobody looks: a request or a scrape builds what it reads, an open page keeps the view current."""
        if self._signature() == self.signature:
            return
        try:
            built = await self.loop.run_in_executor(None, self.refresh)
        except Exception as exc:  # a bad object must not stop the page: log it, keep the last view
            log.warning("dashboard: view not rebuilt: %s: %s", exc.__class__.__name__, str(exc)[:300])
            built = False
        if built:
            self.changed_async.set()
            self.changed_async = asyncio.Event()

    async def _follow(self) -> None:
        """While a page is open (a stream), keep its view current: check every ``refresh_s``, at most once per build.
        Node transitions are noted for the timeline even while nobody looks (a cheap pass over the nodes)."""
        nodes_seen = -1
        while not self.controller.stop_event.is_set():
            if self.streams:
                await self._fresh()
            elif self.controller.nodes.generation != nodes_seen:
                nodes_seen = self.controller.nodes.generation
                await self.loop.run_in_executor(None, self._note_nodes_now)
            await asyncio.sleep(max(self.refresh_s, self.build_s))

    def _note_nodes_now(self) -> None:
        with self.building:
            self._note_nodes(self.controller.nodes.snapshot())

    def app(self):
        from aiohttp import web

        app = web.Application(middlewares=[self._guard()], client_max_size=64 * 1024)
        app.router.add_get("/", self.index)
        app.router.add_get("/static/app.js", self.static)
        app.router.add_get("/static/app.css", self.static)
        app.router.add_get("/healthz", self.healthz)
        app.router.add_get("/favicon.ico", self.no_icon)
        app.router.add_get("/login", self.login_page)
        app.router.add_post("/login", self.login)
        app.router.add_post("/logout", self.logout)
        app.router.add_get("/metrics", self.prometheus)
        app.router.add_get("/api/summary", self.summary)
        app.router.add_get("/api/fleets", self.fleets)
        app.router.add_get("/api/software", self.software)
        app.router.add_get("/api/placement.svg", self.placement)
        app.router.add_get("/api/stream", self.stream)
        app.router.add_get("/api/logs", self.logs)
        app.router.add_get("/api/graph", self.graph)
        for name in LISTS:
            app.router.add_get(f"/api/{name}", self.listing)
        return app

    # -- security ---------------------------------------------------------------------------------
    @staticmethod
    def _headers(response):
        response.headers.setdefault("X-Content-Type-Options", "nosniff")
        response.headers.setdefault("X-Frame-Options", "DENY")
        response.headers.setdefault("Referrer-Policy", "no-referrer")
        response.headers.setdefault(
            "Content-Security-Policy",
            "default-src 'none'; script-src 'self'; style-src 'self'; img-src 'self'; connect-src 'self'; "
            "form-action 'self'; frame-ancestors 'none'; base-uri 'none'",
        )
        response.headers.setdefault("Cache-Control", "no-store")
        return response

    def _token(self, request) -> str:
        header = request.headers.get("Authorization", "")
        if header[:7].lower() == "bearer ":
            return header[7:].strip()
        return self.auth.session_token(request.cookies.get(COOKIE, "")) if self.auth else ""

    async def _verdict(self, request, path: str):
        token = self._token(request)
        return await asyncio.get_running_loop().run_in_executor(None, self.auth.check, token, path)

    def own_host(self, host: str | None) -> bool:
        """Whether ``host`` (a request's Host header) names this dashboard: one of its loopback names, or the
        address it is bound to, with its port (the scheme's default port may be left out)."""
        if not host or len(host) > 300:
            return False
        host = host.strip().lower()
        if host.startswith("["):
            name, _bracket, rest = host.partition("]")
            name += "]"
            if rest and not rest.startswith(":"):
                return False
            port = rest[1:]
        else:
            name, colon, port = host.partition(":")
            port = port if colon else ""
        bound = f"[{self.host.lower()}]" if ":" in self.host else self.host.lower()
        default = "443" if self.tls else "80"
        return name in (*LOOPBACK_NAMES, bound) and (port or default) == str(self.port)

    def _guard(self):
        from aiohttp import web

        @web.middleware
        async def guard(request, handler):
            if self.auth is None and not self.own_host(request.headers.get("Host")):
                shown = repr(request.headers.get("Host", "")[:80]) if request.headers.get("Host") else "none"
                names = ", ".join(f"{name}:{self.port}" for name in LOOPBACK_NAMES)
                return self._headers(web.Response(status=421, text=(
                    f"this dashboard answers only as {names} (Host {shown} refused: it has no login, so another "
                    "name could be a web page reading it through DNS rebinding)\n")))  # fmt: skip
            public = request.path in ("/healthz", "/login", "/logout", "/static/app.css", "/favicon.ico")
            if self.auth is not None and not public:
                path = METRICS_PATH if request.path == "/metrics" else DASHBOARD_PATH
                verdict = await self._verdict(request, path)
                if verdict.status != 200:
                    if request.path == "/" and verdict.status == 401:
                        raise web.HTTPSeeOther("/login")
                    response = web.json_response({"error": verdict.why}, status=verdict.status)
                    if verdict.status == 401:
                        response.headers["WWW-Authenticate"] = 'Bearer realm="kuberos"'
                    return self._headers(response)
            try:
                response = await handler(request)
            except web.HTTPException as exc:
                self._headers(exc)
                raise
            return self._headers(response)

        return guard

    # -- handlers -----------------------------------------------------------------------------------
    async def index(self, request):
        from aiohttp import web

        return web.Response(text=dashboard_page.HTML, content_type="text/html")

    async def static(self, request):
        from aiohttp import web

        if request.path.endswith(".js"):
            return web.Response(text=dashboard_page.SCRIPT, content_type="application/javascript")
        return web.Response(text=dashboard_page.STYLE, content_type="text/css")

    async def no_icon(self, request):
        from aiohttp import web

        return web.Response(status=204)

    async def healthz(self, request):
        from aiohttp import web

        return web.json_response({"ok": True, "generation": self.view.generation})

    async def login_page(self, request):
        from aiohttp import web

        if self.auth is None:
            raise web.HTTPSeeOther("/")
        failed = request.query.get("failed", "")
        return web.Response(text=dashboard_page.login_html(failed), content_type="text/html")

    async def login(self, request):
        from aiohttp import web

        if self.auth is None:
            raise web.HTTPSeeOther("/")
        form = await request.post()
        token = str(form.get("token", "")).strip()
        verdict = await asyncio.get_running_loop().run_in_executor(None, self.auth.check, token, DASHBOARD_PATH)
        if verdict.status != 200:
            raise web.HTTPSeeOther("/login?failed=" + ("forbidden" if verdict.status == 403 else "unknown"))
        response = web.HTTPSeeOther("/")
        response.set_cookie(
            COOKIE, self.auth.open_session(token), httponly=True, samesite="Strict", path="/", secure=request.secure,
            max_age=int(self.auth.session_s),
        )  # fmt: skip
        raise response

    async def logout(self, request):
        from aiohttp import web

        if self.auth is not None:
            self.auth.close_session(request.cookies.get(COOKIE, ""))
        response = web.HTTPSeeOther("/login" if self.auth else "/")
        response.del_cookie(COOKIE, path="/")
        raise response

    async def prometheus(self, request):
        from aiohttp import web
        from prometheus_client import CONTENT_TYPE_LATEST, generate_latest

        await self._fresh()
        body = await asyncio.get_running_loop().run_in_executor(None, generate_latest, self.metrics.registry)
        return web.Response(body=body, headers={"Content-Type": CONTENT_TYPE_LATEST})

    def _json(self, data):
        from aiohttp import web

        return web.json_response(data, dumps=lambda d: json.dumps(d, separators=(",", ":")))

    async def summary(self, request):
        await self._fresh()
        view = self.view
        return self._json({"generation": view.generation, "built_at": view.built_at, "build_s": round(self.build_s, 4),
                           "auth": self.auth is not None, **view.summary})  # fmt: skip

    async def fleets(self, request):
        await self._fresh()
        return self._json({"generation": self.view.generation, "fleets": self.view.fleets})

    async def software(self, request):
        await self._fresh()
        return self._json({"generation": self.view.generation, **self.view.software})

    async def listing(self, request):
        await self._fresh()
        view = self.view
        name = request.path.rsplit("/", 1)[1]
        keys, fields = LISTS[name]
        rows = getattr(view, name)
        query = {k: request.query.get(k, "") for k in (*keys, "q")}
        found = select(rows, query, fields)
        facets = {}
        for key in FACETS[name]:
            counts: dict[str, int] = {}
            for row in rows:
                value = row.get(key)
                label = ("true" if value else "false") if isinstance(value, bool) else str(value or "")
                counts[label] = counts.get(label, 0) + 1
            facets[key] = dict(sorted(counts.items()))
        result = page(found, request.query.get("page", 0), request.query.get("size", 100))
        return self._json({"generation": view.generation, "facets": facets, **result})

    async def placement(self, request):
        from aiohttp import web

        await self._fresh()
        view = self.view
        key = request.query.get("deployment", "") or next(iter(view.placements), "")
        placement = view.placements.get(key)
        if placement is None:
            raise web.HTTPNotFound(text=f"no deployment {key!r}")
        robots = sorted({r for inst in placement.instances for r in inst.robots})
        text = request.query.get("q", "").strip().lower()
        chosen = [r for r in robots if text in r.lower()]
        try:
            limit = max(1, min(int(request.query.get("robots", MAP_ROBOTS)), 200))
        except ValueError:
            limit = MAP_ROBOTS
        part = live_placement(view, key, set(chosen[:limit]))
        svg = await asyncio.get_running_loop().run_in_executor(None, render_placement_svg, part)
        shown = f"{min(len(chosen), limit)}/{len(robots)}"
        return web.Response(text=svg, content_type="image/svg+xml", headers={"X-KubeROS-Robots": shown})

    async def logs(self, request):
        """The last lines of one module instance (``?instance=``), read when asked: the page asks every 2 s while
        its log panel is open."""
        from aiohttp import web

        await self._fresh()
        instance = request.query.get("instance", "")
        row = next((r for r in self.view.modules if r.get("instance") == instance and r.get("namespace")), None)
        if row is None:
            raise web.HTTPNotFound(text=f"no module instance {instance!r}")
        lines = request.query.get("lines", DASHBOARD_LINES)
        try:
            found = await asyncio.get_running_loop().run_in_executor(
                None, instance_log, self.controller.kube, row["namespace"], instance, int(lines)
            )
        except ValueError:
            raise web.HTTPBadRequest(text="lines must be a whole number") from None
        except Exception as exc:  # the API server's refusal or an unreachable cluster: said, not raised
            found = {"instance": instance, "missing": f"the log could not be read: {exc.__class__.__name__}"}
        return self._json({**found, "robot": row.get("robot", ""), "module": row.get("module", "")})

    async def graph(self, request):
        """One deployment's ROS graph per robot, as its last check saw it (``?deployment=namespace/name``; ``q``:
        the robots whose names contain it, at most ``robots``, default 12)."""
        await self._fresh()
        graphs = self.view.graphs
        key = request.query.get("deployment", "") or next(iter(sorted(graphs)), "")
        robots = graphs.get(key, {})
        text = request.query.get("q", "").strip().lower()
        try:
            limit = max(1, min(int(request.query.get("robots", MAP_ROBOTS)), 200))
        except ValueError:
            limit = MAP_ROBOTS
        chosen = sorted(r for r in robots if text in r.lower())
        return self._json({"generation": self.view.generation, "deployment": key, "deployments": sorted(graphs),
                           "robots": {r: robots[r] for r in chosen[:limit]}, "shown": min(len(chosen), limit),
                           "total": len(robots)})  # fmt: skip

    async def stream(self, request):
        from aiohttp import web

        if self.streams >= MAX_STREAMS:
            raise web.HTTPServiceUnavailable(text="too many open dashboards")
        response = web.StreamResponse(headers={"Content-Type": "text/event-stream", "Cache-Control": "no-store"})
        self._headers(response)
        await response.prepare(request)
        await self._fresh()
        self.streams += 1
        try:
            sent = -1
            while not self.controller.stop_event.is_set():
                if self.view.generation != sent:
                    sent = self.view.generation
                    await response.write(f"event: change\ndata: {json.dumps({'generation': sent})}\n\n".encode())
                waiter = self.changed_async
                try:
                    await asyncio.wait_for(waiter.wait(), timeout=15)
                except TimeoutError:
                    await response.write(b": keep-alive\n\n")
        except (ConnectionResetError, asyncio.CancelledError):
            pass
        finally:
            self.streams -= 1
        return response
