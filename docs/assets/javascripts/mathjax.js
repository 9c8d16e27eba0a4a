// MathJax 3 configuration for the formulas written with pymdownx.arithmatex (generic mode): arithmatex
// wraps each formula in an element of class "arithmatex" with \( \) or \[ \] delimiters, and only
// those elements are typeset. The equations carry the paper's numbers explicitly (\tag{n}).
// MathJax itself is loaded after this file (mkdocs.yml, extra_javascript) from a CDN: without a
// network connection the formulas stay as their LaTeX source.
window.MathJax = {
  tex: {
    inlineMath: [["\\(", "\\)"]],
    displayMath: [["\\[", "\\]"]],
    processEscapes: true,
    processEnvironments: true,
  },
  options: {
    ignoreHtmlClass: ".*|",
    processHtmlClass: "arithmatex",
  },
};

// Typeset again whenever Material swaps in a page without reloading the scripts (instant navigation).
document$.subscribe(() => {
  if (!window.MathJax.typesetPromise) return; // MathJax not loaded (yet, or offline)
  MathJax.startup.output.clearCache();
  MathJax.typesetClear();
  MathJax.texReset();
  MathJax.typesetPromise();
});
