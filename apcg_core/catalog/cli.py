"""`apcg catalog ...`: list, show (contact sheet), export and add types."""

from __future__ import annotations

import json

from ..outputs import FILE, PICTURE_SUFFIXES, add_output
from .importer import EXPORT_SUFFIXES


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
    add_output(ex, "-o", "--output", kind=FILE, suffixes=EXPORT_SUFFIXES, required=True,
               help="FILE.{ply,obj,stl,glb}")
    ex.set_defaults(func=_export)

    sh = cs.add_parser("show", help="draw top / side / front views into a PNG")
    sh.add_argument("names", nargs="*", help="types to draw (default: all)")
    add_output(sh, "-o", "--output", kind=FILE, suffixes=PICTURE_SUFFIXES, required=True,
               help="sheet.png (or .pdf, .svg)")
    sh.add_argument("--columns", type=int, default=6)
    sh.add_argument("--dpi", type=int, default=70)
    sh.set_defaults(func=_show)

    from .formats import FORMATS

    kinds = "; ".join(f"{f.name} ({' '.join(f.suffixes)}): {f.via}" for f in FORMATS)
    ad = cs.add_parser("add", help="register an imported model as a new type",
                       description="Import a model into the body frame (x nose, y left wing, "
                                   "z up), in metres, and store it in the user catalog "
                                   "($APCG_DATA_DIR/catalog or ~/.local/share/apcg/catalog). "
                                   f"Formats: {kinds}. The unit and axes the file declares "
                                   "are used unless given; a size implausible for the kind "
                                   "is refused unless --force.")
    ad.add_argument("file")
    ad.add_argument("--name", required=True)
    size = ad.add_mutually_exclusive_group()
    size.add_argument("--length-m", type=float,
                      help="scale so the nose-to-tail length is this (overrides the file)")
    size.add_argument("--unit-scale", type=float,
                      help="file units -> metres factor, e.g. 0.001 for millimetres "
                           "(overrides the unit the file declares)")
    ad.add_argument("--forward", help="the file's nose axis: X, -X, Y, -Y, Z, -Z (default: "
                                      "what the file declares, else X)")
    ad.add_argument("--up", help="the file's up axis (default: what the file declares, else Z)")
    ad.add_argument("--objects", metavar="PATTERN",
                    help="take only the objects whose name matches (shell patterns, "
                         "comma-separated, e.g. 'Fuselage*,Wing*')")
    ad.add_argument("--kind", choices=("aircraft", "drone"), default="aircraft")
    ad.add_argument("--category", default="user",
                    help="the type's category: one of the built-in types' ("
                         "airliner_narrowbody, fighter, multirotor_drone, ...: `apcg catalog "
                         "list`) or user (default)")
    ad.add_argument("--reflectivity", type=float, metavar="R",
                    help="diffuse reflectivity at the lidar's wavelength, in (0, 1], for "
                         "--sensor scans (default: the category's, SPEC section 8)")
    ad.add_argument("--dry-run", action="store_true",
                    help="import, check and report (and --preview) without adding the type")
    ad.add_argument("--force", action="store_true",
                    help="two things at once: replace your type of the same name (names are "
                         "compared ignoring case, spaces, '-' and '_') and an existing "
                         "--preview; and add a model whose size is implausible for its kind "
                         "(with a warning) instead of refusing it")
    add_output(ad, "--preview", kind=FILE, suffixes=PICTURE_SUFFIXES, metavar="PNG",
               help="draw top / side / front views of the imported model into PNG (or .pdf, "
                    ".svg)")
    ad.set_defaults(func=_add)

    rm = cs.add_parser("remove", help="remove one of your types from the catalog",
                       description="Remove a type you added (its entry and its mesh); "
                                   "built-in types stay.")
    rm.add_argument("name", help="the type's name")
    rm.set_defaults(func=_remove)


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
    path = export_mesh(cat.mesh(args.name), args.output)
    print(f"wrote {path}")
    return 0


def _show(args) -> int:
    from .sheet import contact_sheet
    path = contact_sheet(_catalog(), args.names or None, args.output, args.columns, args.dpi)
    print(f"wrote {path}")
    return 0


def _warn(message: str) -> None:
    """Every warning of `apcg catalog`, with the command's prefix, on stderr."""
    import sys
    print(f"apcg catalog: warning: {message}", file=sys.stderr)


def _add(args) -> int:
    from .checks import axes_warning, check_size, hole_entry_share
    from .importer import _default_forward, import_model

    # the whole request is checked before anything is said or written: the name, kind and
    # category, the reflectivity, the file and its import, the size (a dry run refuses what
    # the real add refuses); then the report and its warnings, then the preview and the add
    name = _catalog().check_new_type(args.name, args.kind, args.force, args.category)
    if args.reflectivity is not None:
        from ..sensor.reflectivity import check_reflectivity
        check_reflectivity(args.reflectivity, "--reflectivity")
    mesh, rep = import_model(args.file, forward=args.forward, up=args.up,
                             unit_scale=args.unit_scale, length_m=args.length_m,
                             objects=args.objects, guess=args.forward is None or args.up is None)
    problem = check_size(mesh.extents, args.kind, args.force, rep.scale,
                         name=f"{args.file} (type {name!r})")
    say = print
    say(f"read {args.file}: {rep.n_faces} triangles, {rep.n_bodies} bodies, "
        f"{'closed' if rep.watertight else 'open'} (origin: {rep.centre})")
    say(f"  objects: {', '.join(rep.objects)}"
        + (f"; skipped: {', '.join(rep.skipped)}" if rep.skipped else ""))
    say(f"  unit: {rep.unit} (x{rep.scale:g})")
    say(f"  axes: {rep.axes}")
    say(f"  extents: length {rep.extents_m[0]:.4g} m, span {rep.extents_m[1]:.4g} m, "
        f"height {rep.extents_m[2]:.4g} m")
    if rep.n_duplicates:
        _warn(f"{args.file}: {rep.n_duplicates} duplicate triangle"
              f"{'s' if rep.n_duplicates != 1 else ''} (on the same three vertices as "
              "another) dropped; a copy would make a closed model read as open")
    if rep.precision:
        _warn(f"{args.file}: {rep.precision}")
    if rep.n_dropped:
        _warn(f"{args.file}: {rep.n_dropped} degenerate (zero-area) triangle"
              f"{'s' if rep.n_dropped != 1 else ''} dropped; the rest is the model")
    warn = axes_warning(rep.guess, rep.forward, rep.up, rep.axes,
                        forward_given=args.forward is not None, up_given=args.up is not None,
                        default_forward=None if rep.forward_declared else _default_forward)
    if warn:
        _warn(f"{args.file}: {warn}")
    holes = hole_entry_share(mesh)
    if holes["share"] > 0.01:
        _warn(f"{holes['share']:.1%} of lidar rays enter {args.file} through holes and return "
              "from its inside (open windows, missing panels); the scans will show inner "
              "walls. Close the holes in a modeller, or pick the outer skin with --objects "
              "(docs/IMPORT.md).")
    if problem:  # only with --force: check_size refused it otherwise
        _warn(f"{name!r}: {problem}; "
              + ("it would be added anyway (--force)" if args.dry_run
                 else "added anyway (--force)"))
    if args.preview:
        from .sheet import three_views
        say(f"wrote {three_views(mesh, args.preview, title=name)}")
    if args.dry_run:
        say("dry run: nothing added")
        return 0
    cat = _catalog()
    # add_user_type checks again (name, size) under the catalog's lock
    t = cat.add_user_type(name, mesh, args.kind, args.category, source=args.file,
                          force=args.force, unit_scale=rep.scale,
                          reflectivity=args.reflectivity)
    replaced = cat.last_replaced
    if replaced is not None:
        say(f"replaced {replaced.name!r} by {t.name!r} as type index {t.index} (--force)")
    else:
        say(f"added {t.name!r} as type index {t.index}")
    return 0


def _remove(args) -> int:
    t = _catalog().remove_user_type(args.name)
    print(f"removed {t.name!r} (type index {t.index})")
    return 0
