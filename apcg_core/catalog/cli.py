"""`apcg catalog ...`: list, show (contact sheet), export and add types."""

from __future__ import annotations

import json


def register(sub) -> None:
    p = sub.add_parser("catalog", help="list, draw, export and add aircraft types",
                       description="The aircraft catalog: built-in types and your imported "
                                   "models.")
    cs = p.add_subparsers(dest="catalog_command", metavar="ACTION", required=True)

    ls = cs.add_parser("list", help="list the types")
    ls.add_argument("--json", action="store_true", help="print JSON (a list of objects)")
    ls.set_defaults(func=_list)

    ex = cs.add_parser("export", help="write a type's mesh (body frame, metres)")
    ex.add_argument("name", help="type name or index")
    ex.add_argument("-o", "--output", required=True, help="FILE.{ply,obj,stl,glb}")
    ex.set_defaults(func=_export)

    sh = cs.add_parser("show", help="draw top / side / front views into a PNG")
    sh.add_argument("names", nargs="*", help="types to draw (default: all)")
    sh.add_argument("-o", "--output", required=True, help="sheet.png")
    sh.add_argument("--columns", type=int, default=6)
    sh.add_argument("--dpi", type=int, default=70)
    sh.set_defaults(func=_show)

    ad = cs.add_parser("add", help="register an imported model as a new type",
                       description="Import a model (OFF, OBJ, STL, PLY, glTF/GLB) into the body "
                                   "frame and store it in the user catalog "
                                   "($APCG_DATA_DIR/catalog or ~/.local/share/apcg/catalog).")
    ad.add_argument("file")
    ad.add_argument("--name", required=True)
    size = ad.add_mutually_exclusive_group(required=True)
    size.add_argument("--length-m", type=float, help="scale so the nose-to-tail length is this")
    size.add_argument("--unit-scale", type=float, help="file units -> metres factor")
    ad.add_argument("--forward", default="X", help="the file's nose axis (X, -X, Y, ...)")
    ad.add_argument("--up", default="Z", help="the file's up axis")
    ad.add_argument("--kind", choices=("aircraft", "drone"), default="aircraft")
    ad.add_argument("--category", default="user")
    ad.set_defaults(func=_add)


def _catalog():
    from .catalog import default_catalog
    return default_catalog()


def _list(args) -> int:
    cat = _catalog()
    rows = [t.summary() for t in cat]
    if args.json:
        print(json.dumps(rows, indent=1))
        return 0
    print(f"{'index':>5}  {'name':24s} {'kind':8s} {'category':20s} "
          f"{'length':>7} {'span':>7} {'height':>7}")
    for r in rows:
        print(f"{r['index']:>5}  {r['name']:24s} {r['kind']:8s} {r['category']:20s} "
              f"{r['length_m']:7.2f} {r['span_m']:7.2f} {r['height_m']:7.2f}")
    return 0


def _export(args) -> int:
    from .importer import export_mesh
    cat = _catalog()
    key = int(args.name) if args.name.isdigit() else args.name
    path = export_mesh(cat.mesh(key), args.output)
    print(f"wrote {path}")
    return 0


def _show(args) -> int:
    from .sheet import contact_sheet
    path = contact_sheet(_catalog(), args.names or None, args.output, args.columns, args.dpi)
    print(f"wrote {path}")
    return 0


def _add(args) -> int:
    from .importer import import_model
    mesh, rep = import_model(args.file, forward=args.forward, up=args.up,
                             unit_scale=args.unit_scale, length_m=args.length_m)
    t = _catalog().add_user_type(args.name, mesh, args.kind, args.category, source=args.file)
    print(f"added {t.name!r} as type index {t.index}: {rep.n_faces} triangles, "
          f"{rep.n_bodies} bodies, {'closed' if rep.watertight else 'open'} "
          f"(origin: {rep.centre}), extents {[round(e, 3) for e in rep.extents_m]} m")
    return 0
