#!/bin/sh
# Build the course tracer and one binary per compile-time switch into OUTDIR.
#   tests/ctracer/build.sh OUTDIR        (CC and CFLAGS may be overridden from the environment)
# Binaries: course (the notes) and course_<switch> for each switch below.
set -eu
if [ $# -ne 1 ]; then
    echo "usage: $0 OUTDIR" >&2
    exit 64
fi
out=$1
case $0 in */*) here=${0%/*} ;; *) here=. ;; esac
src=$(cd "$here" && pwd)/course.c
CC=${CC:-cc}
CFLAGS=${CFLAGS:--std=c99 -O2 -Wall -Wextra}
if ! command -v "$CC" >/dev/null 2>&1; then
    echo "$0: C compiler '$CC' not found (install a C compiler, e.g. apt-get install gcc)" >&2
    exit 1
fi
mkdir -p "$out"
build() {   # build NAME [FLAGS...]
    name=$1
    shift
    # shellcheck disable=SC2086
    if ! "$CC" $CFLAGS "$@" -o "$out/$name" "$src" -lm; then
        echo "$0: building $name failed" >&2
        exit 1
    fi
}
build course
build course_edges_open      -DEDGES_OPEN
build course_clip_ge         -DCLIP_GE
build course_ties_last       -DTIES_LAST
build course_tmin            -DTMIN=1e-4
build course_clip_spheres    -DCLIP_SPHERES
build course_reflect_segment -DREFLECT_SEGMENT
build course_rows_shifted    -DROWS_SHIFTED
build course_tile_off        -DTILE_OFF=1000
build course_tile_noproject  -DTILE_NOPROJECT
build course_alias_xform     -DALIAS_XFORM
build course_inv_square      -DINV_SQUARE
build course_no_shadows      -DNO_SHADOWS
build course_spot_full_angle -DSPOT_FULL_ANGLE
build course_tile_add_first  -DTILE_ADD_FIRST
build course_quant_round     -DQUANT_ROUND
build course_rows_flipped    -DROWS_FLIPPED
build course_dir_not_unit    -DDIR_NOT_UNIT
build course_self_shadow     -DSELF_SHADOW
build course_tile_swap       -DTILE_SWAP
build course_amb_after       -DAMB_AFTER
build course_off_by_one      -DOFF_BY_ONE
build course_hdr_256         -DHDR_256
build course_emis_swap       -DEMIS_SWAP
build course_clamp_after     -DCLAMP_AFTER
echo "built 25 binaries in $out"
