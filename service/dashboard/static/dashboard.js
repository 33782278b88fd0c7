// Live state, stage and progress of the jobs on a dashboard page.
// Every element with data-job-id holds one job's .js-state, .js-stage, .js-progress,
// .js-progress-text (and .js-error); the poller asks /dashboard/api/jobs for the jobs that
// are not finished yet and updates them in place. A job page reloads once its job
// finishes, to show the metrics and previews published with it.
(function () {
  "use strict";

  var body = document.body;
  var base = body.dataset.base || "/dashboard";
  var pollMs = parseInt(body.dataset.pollMs || "1000", 10);

  function applyWidth(bar) {
    var pct = parseFloat(bar.dataset.percent || "0");
    if (!isFinite(pct)) pct = 0;
    var fill = bar.querySelector(".js-fill");
    if (fill) fill.style.width = Math.max(0, Math.min(100, pct)) + "%";
  }

  function rows() {
    return Array.prototype.slice.call(document.querySelectorAll(".js-job[data-job-id]"));
  }

  function setText(root, selector, text) {
    root.querySelectorAll(selector).forEach(function (el) {
      if (el.textContent !== text) el.textContent = text;
    });
  }

  function update(root, s) {
    root.querySelectorAll(".js-state").forEach(function (el) {
      el.textContent = s.state;
      el.className = "state state-" + s.state.toLowerCase() + " js-state";
    });
    setText(root, ".js-stage", s.stage || (root.classList.contains("job-row") ? "" : "-"));
    root.querySelectorAll(".js-progress").forEach(function (bar) {
      bar.dataset.percent = String(s.percent);
      bar.setAttribute("aria-valuenow", String(s.percent));
      applyWidth(bar);
    });
    setText(root, ".js-progress-text",
      s.done + " / " + s.total + " (" + Math.round(s.percent) + "%)");
    root.querySelectorAll(".js-error").forEach(function (el) {
      el.textContent = s.error || "";
      el.hidden = !s.error;
    });
    var wasTerminal = root.dataset.terminal === "true";
    root.dataset.terminal = s.terminal ? "true" : "false";
    if (s.terminal && !wasTerminal && root.dataset.reloadWhenDone === "true") {
      window.setTimeout(function () { window.location.reload(); }, 300);
    }
  }

  function poll() {
    var live = rows().filter(function (r) { return r.dataset.terminal !== "true"; });
    if (live.length === 0) return;
    var query = live.map(function (r) {
      return "id=" + encodeURIComponent(r.dataset.jobId);
    }).join("&");
    fetch(base + "/api/jobs?" + query, {
      credentials: "same-origin",
      headers: { "Accept": "application/json" },
      cache: "no-store"
    }).then(function (resp) {
      if (resp.status === 401) {
        window.location.assign(base + "/login?next=" +
          encodeURIComponent(window.location.pathname + window.location.search));
        return null;
      }
      return resp.ok ? resp.json() : null;
    }).then(function (data) {
      if (!data) return;
      var byId = {};
      data.jobs.forEach(function (s) { byId[s.id] = s; });
      live.forEach(function (r) {
        var s = byId[r.dataset.jobId];
        if (s) update(r, s);
      });
    }).catch(function () { /* the next tick tries again */ })
      .then(schedule);
  }

  function schedule() {
    if (rows().some(function (r) { return r.dataset.terminal !== "true"; })) {
      window.setTimeout(poll, pollMs);
    }
  }

  document.querySelectorAll(".js-progress").forEach(applyWidth);
  schedule();
})();
