"""The internal dashboard: server-rendered pages under ``/dashboard`` (``router.py``;
``mount.py`` installs them).

Jinja2 templates and a little vanilla JavaScript that polls a JSON route for live
progress; no front-end build. Browsers log in with an API key (``auth.py``) and see only
that key's objects.
"""
