// MathJax renders the formulas of pymdownx.arithmatex (generic mode: \( \) and \[ \] in
// elements of class "arithmatex"). The renderer itself is vendored, so that the site shows
// formulas without network access: mathjax/tex-svg.js is es5/tex-svg.js of the npm package
// mathjax 3.2.2 (Apache-2.0, mathjax/LICENSE); SVG output needs no font files.
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
  svg: {
    fontCache: "global",
  },
};
