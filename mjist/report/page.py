"""``report.html``: one self-contained page (no network) drawing a ``Report``.

plotly's offline bundle (inlined) draws each layer as a ``Mesh3d``; the meshes are embedded once
as base64 float32/int32 arrays and a few lines of script move them between the views (4x4 per
moved layer), so switching candidates costs no extra copies of the arches. A contact map is
drawn per vertex in its legend's colours (a stepped colour scale over the band index).
"""
from __future__ import annotations

import base64
import html
import json
from pathlib import Path

import numpy as np

from .read import Report


def _b64(a, dtype) -> str:
    return base64.b64encode(np.ascontiguousarray(a, dtype=dtype).tobytes()).decode("ascii")


def _rgb(c) -> str:
    return "rgb({},{},{})".format(*(int(round(255 * x)) for x in c[:3]))


def _layer_json(layer, legend) -> dict:
    out = {"name": layer.name, "v": _b64(layer.vertices, "<f4"), "f": _b64(layer.faces, "<i4"),
           "colour": _rgb(layer.colour), "opacity": layer.opacity}
    if layer.band is not None and legend:
        out["band"] = _b64(layer.band, "<i1")
    return out


def _table(title, header, rows) -> str:
    head = "".join(f"<th>{html.escape(str(h))}</th>" for h in header)
    body = "".join("<tr>" + "".join(f"<td>{html.escape(str(c))}</td>" for c in r) + "</tr>" for r in rows)
    return f"<h3>{html.escape(title)}</h3><table><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>"


_STYLE = """
body{font-family:system-ui,sans-serif;margin:0;background:#fafafa;color:#222}
header{padding:10px 18px;background:#2f3b4c;color:#fff} header h1{margin:0;font-size:20px}
header p{margin:4px 0 0;font-size:13px;opacity:.9}
#main{display:flex;gap:12px;padding:10px 18px} #plot{flex:1;height:640px;background:#fff;border:1px solid #ddd}
#side{width:300px;font-size:13px} #side button{display:block;width:100%;margin:3px 0;padding:6px;text-align:left;
border:1px solid #bbb;background:#fff;cursor:pointer;border-radius:4px} #side button.active{background:#2f3b4c;color:#fff}
#note{margin:8px 0;min-height:36px;color:#444} .swatch{display:inline-block;width:16px;height:12px;margin-right:6px;
vertical-align:middle;border:1px solid #888} #legend div{margin:2px 0}
#tables{padding:0 18px 24px} table{border-collapse:collapse;font-size:12px;margin-bottom:10px}
td,th{border:1px solid #ccc;padding:3px 7px;text-align:left} th{background:#eef1f5}
"""

_SCRIPT = r"""
(function(){
const R = JSON.parse(document.getElementById('mjist-data').textContent);
function dec(s, T){const b=atob(s);const u=new Uint8Array(b.length);for(let i=0;i<b.length;i++)u[i]=b.charCodeAt(i);
  return new T(u.buffer);}
const base = R.layers.map(L => ({v: dec(L.v, Float32Array), f: dec(L.f, Int32Array), band: L.band ? dec(L.band, Int8Array) : null}));
const nb = R.legend ? R.legend.length : 0;
// the legend's bands as a stepped colour scale; the last band ("further") in the arch's own colour
function steps(own){const s = []; R.legend.forEach((c, k) => {const col = k === nb - 1 ? own : c[0];
  s.push([k / nb, col]); s.push([(k + 1) / nb, col]);}); return s;}
function moved(i, T){const v = base[i].v, n = v.length / 3, x = new Float32Array(n), y = new Float32Array(n), z = new Float32Array(n);
  for(let j=0;j<n;j++){const a=v[3*j],b=v[3*j+1],c=v[3*j+2];
    x[j]=T[0]*a+T[1]*b+T[2]*c+T[3]; y[j]=T[4]*a+T[5]*b+T[6]*c+T[7]; z[j]=T[8]*a+T[9]*b+T[10]*c+T[11];}
  return [x, y, z];}
const I = [1,0,0,0, 0,1,0,0, 0,0,1,0, 0,0,0,1];
const traces = R.layers.map((L, i) => {const f = base[i].f, m = f.length / 3, ii = new Int32Array(m), jj = new Int32Array(m), kk = new Int32Array(m);
  for(let q=0;q<m;q++){ii[q]=f[3*q];jj[q]=f[3*q+1];kk[q]=f[3*q+2];}
  const [x, y, z] = moved(i, I);
  const t = {type:'mesh3d', name:L.name, x:x, y:y, z:z, i:ii, j:jj, k:kk, opacity:L.opacity, flatshading:false,
    lighting:{ambient:0.45, diffuse:0.8, specular:0.15, roughness:0.6}, lightposition:{x:0, y:-1e5, z:1e5}, hoverinfo:'name'};
  if (base[i].band && nb){const w = new Float32Array(base[i].band.length); for(let j=0;j<w.length;j++) w[j] = base[i].band[j] + 0.5;
    Object.assign(t, {intensity:w, intensitymode:'vertex', colorscale:steps(L.colour), cmin:0, cmax:nb, showscale:false});}
  else t.color = L.colour;
  return t;});
const gd = document.getElementById('plot');
const layout = {margin:{l:0,r:0,t:0,b:0}, showlegend:false, paper_bgcolor:'#ffffff',
  scene:{aspectmode:'data', xaxis:{visible:false}, yaxis:{visible:false}, zaxis:{visible:false}, bgcolor:'#ffffff',
  camera:{eye:{x:R.eye[0], y:R.eye[1], z:R.eye[2]}, up:{x:0, y:0, z:1}}}};
function show(k){const V = R.views[k];
  const xs=[], ys=[], zs=[], vis=[];
  R.layers.forEach((L, i) => {const [x, y, z] = moved(i, V.transforms[L.name] || I); xs.push(x); ys.push(y); zs.push(z);
    vis.push(V.hidden.indexOf(L.name) < 0);});
  Plotly.restyle(gd, {x:xs, y:ys, z:zs, visible:vis});
  document.querySelectorAll('#views button').forEach((b, j) => b.classList.toggle('active', j === k));
  document.getElementById('note').textContent = V.note;
  document.body.dataset.view = String(k);}
const box = document.getElementById('views');
R.views.forEach((V, k) => {const b = document.createElement('button'); b.textContent = V.label; b.onclick = () => show(k); box.appendChild(b);});
Plotly.newPlot(gd, traces, layout, {displaylogo:false, responsive:true}).then(() => {
  const m = /view=(\d+)/.exec(location.hash); show(m ? Math.min(+m[1], R.views.length - 1) : 0);
  document.body.dataset.ready = '1'; document.body.dataset.firstFrameMs = String(Math.round(performance.now()));});
})();
"""


def write_page(report: Report, path) -> Path:
    """Write ``report`` as one HTML file at ``path`` (plotly inlined, nothing fetched)."""
    from plotly.offline import get_plotlyjs

    path = Path(path)
    data = {"layers": [_layer_json(L, report.legend) for L in report.layers],
            "views": [{"label": v.label, "note": v.note, "hidden": list(v.hidden),
                       "transforms": {k: np.asarray(T, float).ravel().tolist() for k, T in v.transforms.items()}}
                      for v in report.views],
            "legend": [[_rgb(c), lab] for c, lab in report.legend] if report.legend else None,
            "eye": list(report.eye)}
    legend = ""
    if report.legend:
        legend = ("<h3>Contact map</h3><div id='legend'>" + "".join(
            f"<div><span class='swatch' style='background:{_rgb(c)}'></span>{html.escape(lab)}</div>"
            for c, lab in report.legend[:-1])
            + f"<div><span class='swatch' style='background:{_rgb(report.layers[0].colour)}'></span><span class='swatch' "
              f"style='background:{_rgb(report.layers[1].colour)}'></span>{html.escape(report.legend[-1][1])}: the arch's "
              "own colour</div>"
            + "<div style='margin-top:4px;color:#555'>distance to the other arch, the estimate within its certified "
              "interval [d − ε, d]</div></div>")
    summary = "".join(f"<p>{html.escape(s)}</p>" for s in report.summary)
    tables = "".join(_table(*t) for t in report.tables)
    payload = json.dumps(data).replace("</", "<\\/")  # no "</script>" inside the script element
    page = f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>{html.escape(report.title)}</title>
<meta http-equiv="Content-Security-Policy" content="default-src 'none'; script-src 'unsafe-inline' 'unsafe-eval'; style-src 'unsafe-inline'; img-src data: blob:; worker-src blob:">
<style>{_STYLE}</style>
<script>{get_plotlyjs()}</script></head>
<body data-kind="{report.kind}"><header><h1>{html.escape(report.title)}</h1>{summary}</header>
<div id="main"><div id="plot"></div><div id="side"><h3>Views</h3><div id="views"></div><div id="note"></div>{legend}
<p style="color:#666">Drag to turn, scroll to zoom. Display meshes are simplified; every figure comes from the full meshes.</p>
</div></div><div id="tables">{tables}</div>
<script type="application/json" id="mjist-data">{payload}</script>
<script>{_SCRIPT}</script>
</body></html>
"""
    path.write_text(page, encoding="utf-8")
    return path
