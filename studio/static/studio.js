// Likeness Studio: give every control an accessible name and keep the E-stop in view.
//
// viser labels a control with a <label for=ID> whose ID is the control's root element; for a slider that root is
// not the focusable thumb (role="slider"), and the number box beside a slider has no label at all. This script
// names them from that label: the thumb gets the label text, the number box "<label> value". It re-runs whenever
// the page's DOM changes (controls are created as the server adds them).
(function () {
  "use strict";

  function labelOf(id) {
    if (!id) return null;
    const lab = document.querySelector('label[for="' + CSS.escape(id) + '"]');
    return lab ? lab.textContent.trim() : null;
  }

  function nameSliders() {
    document.querySelectorAll(".mantine-Slider-root[id], .mantine-RangeSlider-root[id]").forEach(function (root) {
      const name = labelOf(root.id);
      if (!name) return;
      root.querySelectorAll('[role="slider"]').forEach(function (thumb, i, all) {
        const want = all.length > 1 ? name + (i === 0 ? " low" : " high") : name;
        if (thumb.getAttribute("aria-label") !== want) thumb.setAttribute("aria-label", want);
      });
      const row = root.parentElement;
      if (row) {
        row.querySelectorAll("input:not([type=hidden])").forEach(function (box) {
          const want = name + " value";
          if (box.getAttribute("aria-label") !== want) box.setAttribute("aria-label", want);
        });
      }
    });
  }

  function nameOtherInputs() {
    // Any remaining input without a name takes its row's label (e.g. number and text boxes whose label points at
    // a wrapper rather than the input).
    document.querySelectorAll("input:not([type=hidden]), textarea, [role=combobox]").forEach(function (el) {
      if (el.getAttribute("aria-label") || el.labels && el.labels.length) return;
      let node = el, name = null;
      for (let up = 0; up < 8 && node && !name; up++) {
        node = node.parentElement;
        if (!node) break;
        if (node.id) name = labelOf(node.id);
      }
      if (name) el.setAttribute("aria-label", name);
    });
  }

  function pinEstop() {
    // The E-stop stays in view: the panel element holding it (a sibling of the tabs) sticks to the top of the
    // scrolling control panel.
    document.querySelectorAll("button").forEach(function (b) {
      if (b.textContent.trim() !== "E-stop") return;
      b.setAttribute("aria-label", "E-stop");
      let row = b;
      while (row.parentElement && !row.parentElement.querySelector('[role="tablist"]')) row = row.parentElement;
      if (!row.parentElement || row.contains(document.querySelector('[role="tablist"]'))) return;
      if (row.dataset.studioPinned !== "1") {
        row.dataset.studioPinned = "1";
        row.style.position = "sticky";
        row.style.top = "0";
        row.style.zIndex = "20";
        row.style.background = "var(--mantine-color-body)";
      }
      // Sticky positioning holds only up to the nearest clipping ancestor: let the wrappers between the row and the
      // panel's scrolling viewport show their vertical overflow, so the row sticks to the viewport itself.
      let up = row.parentElement;
      for (; up && !up.classList.contains("mantine-ScrollArea-viewport"); up = up.parentElement) {
        const cs = getComputedStyle(up);
        if (cs.overflowY !== "visible") {
          up.style.overflowX = "clip";  // clip, unlike hidden, makes no scroll container: sticky passes through
          up.style.overflowY = "visible";
          up.style.contain = "inline-size";  // and, like hidden did, its content does not widen the panel
        }
      }
      if (up) up.style.overflowX = "hidden";  // the panel scrolls vertically only
    });
  }

  let queued = false;
  function run() {
    queued = false;
    nameSliders();
    nameOtherInputs();
    pinEstop();
  }
  function schedule() {
    if (!queued) {
      queued = true;
      setTimeout(run, 0);
    }
  }
  new MutationObserver(schedule).observe(document.documentElement, {childList: true, subtree: true});
  schedule();
})();
