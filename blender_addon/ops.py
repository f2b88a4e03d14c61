"""Operators: Reconstruct (modal, timer-driven), Cancel, Check backend, Install/Remove Backend, and the image file browser.

The per-tick work is in plain functions (:func:`start_job`, :func:`advance`,
:func:`start_check`, :func:`advance_check`) that take explicit arguments; the
modal operators only call them from their TIMER events, and ``execute()``
(scripts, background mode, where timers never fire) calls them in a loop.
"""

import os
import sys
import time

import bpy
from bpy.props import BoolProperty, EnumProperty, StringProperty

from . import installer, schema
from .backend import BackendError, BackendManager, Request, build_command, weights_argument
from .installer import Installer, InstallError
from .jobs import MASK_IMAGE, Job, JobLimits, UserError, prepare_job, require_photo, work_root
from .props import ADDON_PACKAGE, addon_user_folder, backend_env, get_preferences

TICK_SECONDS = 0.1

# The one backend process of this Blender session, and what is running on it.
manager = BackendManager()


class _Active:
    job = None  # the running Job
    check = None  # the running Check backend Request
    install = None  # the running Installer


active = _Active()


# ---------------------------------------------------------------- plain per-tick functions
def backend_argv(prefs) -> list[str]:
    """``genre serve``'s command line from the preferences (None: the defaults); :class:`BackendError` when unusable."""
    if prefs is None:
        return build_command("")
    weights = weights_argument(prefs.model, prefs.weights and bpy.path.abspath(prefs.weights))
    return build_command(prefs.backend_command and bpy.path.abspath(prefs.backend_command), weights, prefs.device)


def job_limits(prefs) -> JobLimits:
    if prefs is None:
        return JobLimits()
    return JobLimits(startup_timeout=prefs.startup_timeout, timeout=prefs.job_timeout)


def start_job(settings, prefs, status, *, backend: BackendManager | None = None) -> Job:
    """Check the settings, make the job's folder and the request; raises :class:`UserError` / :class:`BackendError`."""
    if active.job is not None and not active.job.finished:
        raise UserError("a reconstruction is already running")
    require_photo(settings)  # the photo first: a missing one is the first thing to say
    if active.install is not None and not active.install.finished:
        raise UserError("the backend is being installed: wait for Install Backend to finish")
    argv = backend_argv(prefs)
    spec = prepare_job(settings, work_root(ADDON_PACKAGE))
    job = Job(spec, backend or manager, argv, job_limits(prefs))
    job.tick()  # start the backend (or send the request) now, not one timer interval later
    active.job = job
    status.running = True
    status.progress = 0.0
    status.stage = job.stage_label
    status.message = ""
    status.message_is_error = False
    status.mask_warning = ""
    old = bpy.data.images.get(MASK_IMAGE)  # the last run's mask picture: not this run's
    if old is not None:
        bpy.data.images.remove(old)
    return job


def advance(job: Job, scene, status, cursor_location, now: float | None = None):
    """One tick: read the backend's news, update ``status``; when the job ends, add the result and clean up.

    Returns None while the job runs, else ``(level, message)`` with level
    ``'INFO'`` (mesh added), ``'WARNING'`` (cancelled) or ``'ERROR'``.
    """
    try:
        job.tick(now)
        sync_options(getattr(scene, "genre", None), job.request.ready)
        status.progress = job.fraction
        status.stage = job.stage_label
        if not job.finished:
            return None
        if job.state == "done":
            try:
                job.apply(scene, cursor_location)
                outcome = ("INFO", job.result_line())
                follow_result(getattr(scene, "genre", None), job.request.result)
            except UserError as exc:
                outcome = ("ERROR", f"GenRe: {exc}")
        elif job.state == "cancelled":
            outcome = ("WARNING", "GenRe: reconstruction cancelled")
        else:
            outcome = ("ERROR", f"GenRe: {job.error}")
    except BaseException as exc:  # never leave the panel stuck in "running"
        job.cancel()
        outcome = ("ERROR", f"GenRe: unexpected error: {type(exc).__name__}: {exc}")
    finish_job(job, status, outcome)
    return outcome


def _set_value(row, value) -> None:
    """Put ``value`` (of the row's kind) into the row's value field."""
    if row.kind == "float" and isinstance(value, (int, float)) and not isinstance(value, bool):
        row.float_value = float(value)
    elif row.kind == "int" and isinstance(value, int) and not isinstance(value, bool):
        row.int_value = value
    elif row.kind == "bool" and isinstance(value, bool):
        row.bool_value = value
    elif row.kind == "choice" and isinstance(value, str):
        row.choice_value = value


_synced: dict = {}


def sync_options(settings, event) -> None:
    """Make the Advanced rows the backend's schema (``event``: its ``ready`` or ``version`` event): a row per option
    (:func:`.schema.rows`), in its order, with its label, help, range and the weights' value; a row kept from before
    keeps its tick and, when ticked, its value; an unticked one shows the weights' value."""
    entries = schema.rows(event)
    if settings is None or not entries:
        return
    key = (id(event), settings.as_pointer(), len(settings.options))
    if _synced.get("key") == key:
        return  # (this event is already in these rows: nothing written on every tick)
    _synced["key"] = key
    rows = settings.options
    wanted = [e["name"] for e in entries]
    for i in reversed(range(len(rows))):
        if rows[i].name not in wanted:
            rows.remove(i)
    for index, e in enumerate(entries):
        row = rows.get(e["name"])
        if row is None:
            row = rows.add()
            row.name = e["name"]
        row.kind, row.label, row.help = e["type"], str(e.get("label") or e["name"]), str(e.get("help") or "")
        row.lo, row.hi = float(e.get("min") or 0.0), float(e.get("max") or 0.0)
        row.lo_open, row.hi_open = bool(e.get("min_open")), bool(e.get("max_open"))
        row.choices = schema.dumps(e.get("choices"))
        row.weights_value = schema.dumps(e.get("default"))
        if not row.override:
            _set_value(row, e.get("default"))  # so that ticking starts from the model's own setting
        current = [r.name for r in rows].index(e["name"])
        if current != index:
            rows.move(current, index)


CACHED_SCHEMA = schema.cached()  # the shipped default weights' options (options_schema.json)


def fill_from_cache(settings) -> bool:
    """Give an Advanced panel without rows the cached schema's (the backend's own replaces them once it has started)."""
    if settings is None or len(settings.options) or CACHED_SCHEMA is None:
        return False
    sync_options(settings, CACHED_SCHEMA)
    return True


@bpy.app.handlers.persistent
def _fill_scenes(*_args):
    for scene in bpy.data.scenes:
        fill_from_cache(getattr(scene, "genre", None))


def follow_result(settings, result) -> None:
    """An unticked row shows the value the backend used (the result's echo of the option, ``protocol.Result``'s
    ``settings``), so that ticking it starts from the shipped mesh rather than from an arbitrary value."""
    used = getattr(result, "settings", None) or {}
    if settings is None:
        return
    for row in settings.options:
        if not row.override and row.name in used:
            _set_value(row, used[row.name])


def finish_job(job: Job, status, outcome) -> None:
    if outcome[0] == "INFO":  # the mask over the photo, for the panel: read before the job's folder goes
        try:
            job.load_mask_overlay()
        except RuntimeError:  # an unreadable picture: the mesh is still there, only the picture is missing
            pass
    job.cleanup()
    if active.job is job:
        active.job = None
    status.running = False
    status.progress = 1.0 if outcome[0] == "INFO" else 0.0
    status.stage = ""
    status.message = outcome[1].removeprefix("GenRe: ")
    status.message_is_error = outcome[0] == "ERROR"
    # the backend's doubt about the mask it used (it covers most of the photo or touches most of its border)
    status.mask_warning = job.mask_warning if outcome[0] == "INFO" else ""


def abandon_job(job: Job, status) -> None:
    """The operator was stopped by Blender (file load, window closed): ask the backend to stop, drop the job."""
    job.cancel()
    try:
        job.tick()
    except Exception:
        pass
    finish_job(job, status, ("WARNING", "GenRe: reconstruction cancelled"))


def start_check(prefs, status, *, backend: BackendManager | None = None) -> Request:
    argv = backend_argv(prefs)
    limits = job_limits(prefs)
    req = (backend or manager).request(argv, "version", startup_timeout=limits.startup_timeout, timeout=30.0)
    active.check = req
    status.checking = True
    status.backend_info = ""
    return req


def advance_check(req: Request, status, now: float | None = None, scene=None):
    """One tick of Check backend; returns None while waiting, else ``(level, message)`` (also shown in the preferences).

    With ``scene``, the Advanced rows are made from the backend's option schema as soon as it is ready."""
    try:
        req.tick(now)
        sync_options(getattr(scene, "genre", None), req.ready)
    except Exception as exc:  # never leave the preferences stuck in "checking"
        req.cancel()
        req.state, req.error = "failed", f"unexpected error: {type(exc).__name__}: {exc}"
    if not req.finished:
        return None
    if req.state == "done":
        ev = req.result
        info = {k: getattr(ev, k, None) or "?" for k in ("version", "protocol", "preset", "threshold", "device", "weights")}
        outcome = ("INFO", f"GenRe backend {info['version']} (protocol {info['protocol']}), preset {info['preset']}, "
                           f"threshold {info['threshold']}, device {info['device']}, weights {info['weights']}")
    elif req.state == "cancelled":
        outcome = ("WARNING", "backend check cancelled")
    else:
        outcome = ("ERROR", f"backend check failed: {req.error}")
    if active.check is req:
        active.check = None
    status.checking = False
    status.backend_info = outcome[1]
    status.backend_ok = outcome[0] == "INFO"
    return outcome


def _redraw(context) -> None:
    wm = context.window_manager
    for window in wm.windows:
        for area in window.screen.areas:
            if area.type in ("VIEW_3D", "PREFERENCES"):
                area.tag_redraw()


def start_install(prefs, status, *, addon_dir: str = os.path.dirname(os.path.abspath(__file__))) -> Installer:
    """Start Install Backend; :class:`InstallError` when it cannot start (no bundle, no Python, no space, busy)."""
    if active.install is not None and not active.install.finished:
        raise InstallError("the backend is already being installed")
    if active.job is not None and not active.job.finished:
        raise InstallError("a reconstruction is running: wait for it to end")
    wheel, requirement = installer.bundle(addon_dir)
    python = bpy.path.abspath(prefs.backend_python) if prefs.backend_python else installer.blender_python(sys.executable)
    folder = bpy.path.abspath(prefs.wheel_folder).rstrip("/\\") if prefs.wheel_folder else ""
    manager.discard()  # a backend running from the environment being replaced would hold its files
    job = Installer(python, addon_user_folder(), wheel, requirement, wheel_folder=folder)
    job.start()
    active.install = job
    status.installing, status.install_progress, status.install_stage = True, 0.0, job.stage
    status.install_line, status.install_message, status.install_ok = "", "", False
    return job


def advance_install(job: Installer, prefs, status):
    """One tick of Install Backend: None while it runs, else ``(level, message)``; when done, Backend Command is the
    new environment's Python."""
    try:
        job.tick()
    except Exception as exc:  # never leave the preferences stuck in "installing"
        job.cancel()
        job.state, job.error = "failed", f"unexpected error: {type(exc).__name__}: {exc}"
    status.install_progress, status.install_stage, status.install_line = job.fraction, job.stage, job.last_line
    if not job.finished:
        return None
    if job.state == "done":
        prefs.backend_command = job.backend_python
        outcome = ("INFO", f"Backend installed in {job.env}")
    elif job.state == "cancelled":
        outcome = ("WARNING", "Install Backend cancelled; nothing was left behind")
    else:
        outcome = ("ERROR", job.error)
    if active.install is job:
        active.install = None
    status.installing = False
    status.install_message, status.install_ok = outcome[1], outcome[0] == "INFO"
    return outcome


def remove_backend(prefs, status) -> str:
    """Delete the add-on's backend environment (and nothing else); clear Backend Command when it named it."""
    if active.install is not None and not active.install.finished:
        raise InstallError("the backend is being installed: cancel that first")
    env = backend_env()
    if not os.path.lexists(env):
        raise InstallError("no backend is installed in the add-on's folder")
    manager.discard()  # stop a backend that runs from it
    installer.remove_env(env)
    if prefs.backend_command and os.path.abspath(bpy.path.abspath(prefs.backend_command)).startswith(os.path.join(env, "")):
        prefs.backend_command = ""
    status.install_message, status.install_ok = f"Backend removed from {env}", True
    status.backend_info, status.backend_ok = "", False
    return status.install_message


# ---------------------------------------------------------------- operators
class _TimerModal:
    """Shared timer plumbing of the two modal operators."""

    _timer = None

    def _add_timer(self, context):
        wm = context.window_manager
        self._timer = wm.event_timer_add(TICK_SECONDS, window=context.window)
        wm.modal_handler_add(self)

    def _remove_timer(self, context):
        if self._timer is not None:
            context.window_manager.event_timer_remove(self._timer)
            self._timer = None


class GENRE_OT_reconstruct(_TimerModal, bpy.types.Operator):
    """Reconstruct a 3D mesh from the chosen photo with GenRe"""

    bl_idname = "genre.reconstruct"
    bl_label = "Reconstruct"
    bl_options = {"UNDO"}

    _job = None

    @classmethod
    def poll(cls, context):
        return context.scene is not None and (active.job is None or active.job.finished)

    def _start(self, context):
        status = context.window_manager.genre_status
        try:
            return start_job(context.scene.genre, get_preferences(context), status)
        except (UserError, BackendError) as exc:
            status.message = str(exc)
            status.message_is_error = True
            self.report({"ERROR"}, f"GenRe: {exc}")
            return None

    def _step(self, context):
        return advance(self._job, context.scene, context.window_manager.genre_status, context.scene.cursor.location.copy())

    def _end(self, context, outcome):
        self.report({outcome[0]}, outcome[1])
        warning = context.window_manager.genre_status.mask_warning
        if outcome[0] == "INFO" and warning:
            self.report({"WARNING"}, f"GenRe: doubtful mask: {warning}")
        return {"FINISHED"} if outcome[0] == "INFO" else {"CANCELLED"}

    def invoke(self, context, event):
        self._job = self._start(context)
        if self._job is None:
            return {"CANCELLED"}
        self._add_timer(context)
        _redraw(context)
        return {"RUNNING_MODAL"}

    def modal(self, context, event):
        if event.type == "ESC" and event.value == "PRESS":
            self._job.cancel()
            return {"RUNNING_MODAL"}
        if event.type != "TIMER":  # any window timer; an extra tick does no harm
            return {"PASS_THROUGH"}
        status = context.window_manager.genre_status
        before = (status.stage, round(status.progress, 3))
        outcome = self._step(context)  # never raises: advance() turns every exception into an outcome
        if outcome is not None or before != (status.stage, round(status.progress, 3)):
            _redraw(context)  # only when the panel changes: redraws are costly with software OpenGL
        if outcome is None:
            return {"RUNNING_MODAL"}
        self._remove_timer(context)
        return self._end(context, outcome)

    def cancel(self, context):
        # Blender ends the operator (new file, window closed): stop the job, leave nothing behind.
        self._remove_timer(context)
        if self._job is not None and not self._job.finished:
            abandon_job(self._job, context.window_manager.genre_status)

    def execute(self, context):
        # Scripts and background mode (no timer events there): the same steps, waiting in place.
        self._job = self._start(context)
        if self._job is None:
            return {"CANCELLED"}
        while True:
            outcome = self._step(context)
            if outcome is not None:
                return self._end(context, outcome)
            time.sleep(0.05)


class GENRE_OT_cancel(bpy.types.Operator):
    """Stop the running reconstruction (the backend stops at its next stage)"""

    bl_idname = "genre.cancel"
    bl_label = "Cancel"

    @classmethod
    def poll(cls, context):
        return active.job is not None and not active.job.finished

    def execute(self, context):
        active.job.cancel()
        context.window_manager.genre_status.stage = "Cancelling"
        return {"FINISHED"}


class GENRE_OT_check_backend(_TimerModal, bpy.types.Operator):
    """Start the backend if needed and show its version, preset and device, or why it failed"""

    bl_idname = "genre.check_backend"
    bl_label = "Check Backend"

    _req = None

    @classmethod
    def poll(cls, context):
        return active.check is None or active.check.finished

    def _start(self, context):
        status = context.window_manager.genre_status
        try:
            return start_check(get_preferences(context), status)
        except BackendError as exc:
            status.checking = False
            status.backend_info = f"backend check failed: {exc}"
            status.backend_ok = False
            self.report({"ERROR"}, f"GenRe: {status.backend_info}")
            return None

    def invoke(self, context, event):
        self._req = self._start(context)
        if self._req is None:
            return {"CANCELLED"}
        self._add_timer(context)
        return {"RUNNING_MODAL"}

    def modal(self, context, event):
        if event.type != "TIMER":
            return {"PASS_THROUGH"}
        outcome = advance_check(self._req, context.window_manager.genre_status, scene=context.scene)
        _redraw(context)
        if outcome is None:
            return {"RUNNING_MODAL"}
        self._remove_timer(context)
        self.report({outcome[0]}, f"GenRe: {outcome[1]}")
        return {"FINISHED"} if outcome[0] == "INFO" else {"CANCELLED"}

    def cancel(self, context):
        self._remove_timer(context)
        if self._req is not None and not self._req.finished:
            self._req.cancel()
            advance_check(self._req, context.window_manager.genre_status)

    def execute(self, context):
        self._req = self._start(context)
        if self._req is None:
            return {"CANCELLED"}
        while True:
            outcome = advance_check(self._req, context.window_manager.genre_status, scene=context.scene)
            if outcome is not None:
                self.report({outcome[0]}, f"GenRe: {outcome[1]}")
                return {"FINISHED"} if outcome[0] == "INFO" else {"CANCELLED"}
            time.sleep(0.05)


class GENRE_OT_install_backend(_TimerModal, bpy.types.Operator):
    """Make a private Python environment in the add-on's folder and install the backend and PyTorch (CPU) into it, \
about 1.2 GB (from the internet, or from the Offline Wheels folder); then check it"""

    bl_idname = "genre.install_backend"
    bl_label = "Install Backend"

    _job = None

    @classmethod
    def poll(cls, context):
        return active.install is None or active.install.finished

    def _start(self, context):
        status = context.window_manager.genre_status
        try:
            return start_install(get_preferences(context), status)
        except (InstallError, OSError) as exc:
            status.install_message, status.install_ok = str(exc), False
            self.report({"ERROR"}, f"GenRe: {exc}")
            return None

    def _end(self, context, outcome):
        self.report({outcome[0]}, f"GenRe: {outcome[1]}")
        if outcome[0] != "INFO":
            return {"CANCELLED"}
        bpy.ops.genre.check_backend("INVOKE_DEFAULT" if self._timer_based else "EXEC_DEFAULT")
        return {"FINISHED"}

    def invoke(self, context, event):
        self._job = self._start(context)
        if self._job is None:
            return {"CANCELLED"}
        self._timer_based = True
        self._add_timer(context)
        _redraw(context)
        return {"RUNNING_MODAL"}

    def modal(self, context, event):
        if event.type != "TIMER":
            return {"PASS_THROUGH"}
        outcome = advance_install(self._job, get_preferences(context), context.window_manager.genre_status)
        _redraw(context)
        if outcome is None:
            return {"RUNNING_MODAL"}
        self._remove_timer(context)
        return self._end(context, outcome)

    def cancel(self, context):
        self._remove_timer(context)
        if self._job is not None and not self._job.finished:
            self._job.cancel()
            advance_install(self._job, get_preferences(context), context.window_manager.genre_status)

    def execute(self, context):
        # Scripts and background mode (no timer events there): the same steps, waiting in place.
        self._job = self._start(context)
        if self._job is None:
            return {"CANCELLED"}
        self._timer_based = False
        while True:
            outcome = advance_install(self._job, get_preferences(context), context.window_manager.genre_status)
            if outcome is not None:
                return self._end(context, outcome)
            time.sleep(0.1)


class GENRE_OT_cancel_install(bpy.types.Operator):
    """Stop installing the backend and delete what was installed so far"""

    bl_idname = "genre.cancel_install"
    bl_label = "Cancel Install"

    @classmethod
    def poll(cls, context):
        return active.install is not None and not active.install.finished

    def execute(self, context):
        active.install.cancel()  # (the modal operator's next tick reports it)
        return {"FINISHED"}


class GENRE_OT_remove_backend(bpy.types.Operator):
    """Delete the backend environment that Install Backend made (nothing else)"""

    bl_idname = "genre.remove_backend"
    bl_label = "Remove Backend"

    @classmethod
    def poll(cls, context):
        return active.install is None or active.install.finished

    def invoke(self, context, event):
        return context.window_manager.invoke_confirm(self, event)

    def execute(self, context):
        try:
            self.report({"INFO"}, f"GenRe: {remove_backend(get_preferences(context), context.window_manager.genre_status)}")
        except (InstallError, OSError) as exc:
            self.report({"ERROR"}, f"GenRe: {exc}")
            return {"CANCELLED"}
        _redraw(context)
        return {"FINISHED"}


class GENRE_OT_show_install_log(bpy.types.Operator):
    """Open the last Install Backend's pip log in a Text Editor window"""

    bl_idname = "genre.show_install_log"
    bl_label = "Show Log"

    def execute(self, context):
        path = os.path.join(addon_user_folder(), installer.LOG_NAME)
        if not os.path.isfile(path):
            self.report({"ERROR"}, "GenRe: no install log yet")
            return {"CANCELLED"}
        text = next((t for t in bpy.data.texts if bpy.path.abspath(t.filepath) == path), None)
        if text is None:
            text = bpy.data.texts.load(path)
        else:
            text.clear()
            with open(path, encoding="utf-8", errors="replace") as fh:
                text.write(fh.read())
        try:  # a new window showing it (a GUI Blender); else the text is there for any Text Editor
            bpy.ops.wm.window_new()
            area = context.window_manager.windows[-1].screen.areas[0]
            area.type = "TEXT_EDITOR"
            area.spaces.active.text = text
        except (RuntimeError, AttributeError, IndexError):
            self.report({"INFO"}, f"GenRe: the log is the text '{text.name}' in the Text Editor")
        return {"FINISHED"}


class GENRE_OT_choose_file(bpy.types.Operator):
    """Choose an image file in the file browser"""

    bl_idname = "genre.choose_file"
    bl_label = "Choose Image"
    bl_options = {"INTERNAL"}

    target: EnumProperty(items=(("PHOTO", "Photo", ""), ("MASK", "Mask", "")), default="PHOTO", options={"HIDDEN"})
    filepath: StringProperty(subtype="FILE_PATH")
    # What the file browser shows: images and folders only.
    filter_image: BoolProperty(default=True, options={"HIDDEN", "SKIP_SAVE"})
    filter_folder: BoolProperty(default=True, options={"HIDDEN", "SKIP_SAVE"})

    @classmethod
    def description(cls, context, properties):
        """The tooltip: the chosen file's whole path (the button shows its name only)."""
        settings = context.scene.genre
        current = settings.photo_path if properties.target == "PHOTO" else settings.mask_path
        what = "photo" if properties.target == "PHOTO" else "mask (optional: white object on black, the photo's size)"
        return f"{bpy.path.abspath(current)}\nClick to choose another {what}" if current else f"Choose the {what}"

    def invoke(self, context, event):
        settings = context.scene.genre
        current = settings.photo_path if self.target == "PHOTO" else settings.mask_path
        if current:
            self.filepath = bpy.path.abspath(current)
        context.window_manager.fileselect_add(self)
        return {"RUNNING_MODAL"}

    def execute(self, context):
        if not os.path.isfile(self.filepath):
            self.report({"ERROR"}, f"GenRe: not a file: {self.filepath}")
            return {"CANCELLED"}
        settings = context.scene.genre
        if self.target == "PHOTO":
            settings.photo_path = self.filepath
            settings.source = "FILE"
        else:
            settings.mask_path = self.filepath
        return {"FINISHED"}


class GENRE_OT_clear_mask(bpy.types.Operator):
    """Use no mask file (the photo's alpha, else the object found in the photo)"""

    bl_idname = "genre.clear_mask"
    bl_label = "Clear Mask"
    bl_options = {"INTERNAL", "UNDO"}

    def execute(self, context):
        context.scene.genre.mask_path = ""
        return {"FINISHED"}


class GENRE_OT_option_help(bpy.types.Operator):
    """What an Advanced option does (its tooltip is the backend's help line)"""

    bl_idname = "genre.option_help"
    bl_label = "About This Option"
    bl_options = {"INTERNAL"}

    option: StringProperty(options={"HIDDEN", "SKIP_SAVE"})

    @classmethod
    def description(cls, context, properties):
        row = context.scene.genre.options.get(properties.option)
        return row.help if row is not None and row.help else cls.__doc__

    def execute(self, context):
        row = context.scene.genre.options.get(self.option)
        if row is not None:
            self.report({"INFO"}, f"{row.label}: {row.help}")
        return {"FINISHED"}


CLASSES = (GENRE_OT_reconstruct, GENRE_OT_cancel, GENRE_OT_check_backend, GENRE_OT_install_backend, GENRE_OT_cancel_install,
           GENRE_OT_remove_backend, GENRE_OT_show_install_log, GENRE_OT_choose_file, GENRE_OT_clear_mask, GENRE_OT_option_help)


def shutdown_backend() -> None:
    """Stop the running job (if any) and the backend process (add-on disabled, Blender quitting)."""
    job = active.job
    if job is not None:
        job.cancel()
        job.cleanup()
        active.job = None
    active.check = None
    if active.install is not None and not active.install.finished:
        active.install.cancel()
    active.install = None
    manager.discard()


def register():
    for cls in CLASSES:
        bpy.utils.register_class(cls)
    bpy.app.handlers.load_post.append(_fill_scenes)
    bpy.app.timers.register(_fill_scenes, first_interval=0.1)  # (bpy.data is closed to add-ons while they register)


def unregister():
    if _fill_scenes in bpy.app.handlers.load_post:
        bpy.app.handlers.load_post.remove(_fill_scenes)
    if bpy.app.timers.is_registered(_fill_scenes):
        bpy.app.timers.unregister(_fill_scenes)
    shutdown_backend()
    for cls in reversed(CLASSES):
        bpy.utils.unregister_class(cls)
