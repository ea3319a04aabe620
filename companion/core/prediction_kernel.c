/* The target's motion over the RMPC horizon: companion/core/prediction.py's stage loop
 * (predict_target_motion), the same IEEE double operations in the same order, for one call
 * instead of ~16 Python iterations. Compiled with -ffp-contract=off -fno-fast-math (no fused
 * multiply-add, every operation rounded as written); cos, sin and atan2 are the C library's,
 * the functions Python's math module calls. companion/core/prediction_kernel.py checks it
 * against the Python loop before first use.
 *
 * in: [v0x, v0y, a0x, a0y, speed, w, yaw_q, dt, has_cap, cap, has_d, d0, d1, d2]
 * out: v_v (horizon x 2), vdot (horizon x 2), psidot (horizon), d_out (horizon x 3, if has_d)
 * returns 0 if every output is finite, 1 if not (the caller then checks them itself).
 */
#include <math.h>

int predict_motion(const double *in, int horizon, double *out)
{
    const double v0x = in[0], v0y = in[1], a0x = in[2], a0y = in[3], speed = in[4];
    const double w = in[5], yaw_q = in[6], dt = in[7], cap = in[9];
    const int has_cap = in[8] != 0.0, has_d = in[10] != 0.0;
    const double d0 = in[11], d1 = in[12], d2 = in[13];
    double *v_v = out, *vdot = out + 2 * horizon, *psidot = out + 4 * horizon;
    double *d_out = out + 5 * horizon;
    const int moving = speed > 1e-6;
    double heading = 0.0, a_along = 0.0, top = INFINITY;
    int n, k, n_out = (has_d ? 8 : 5) * horizon;
    if (moving) {
        heading = atan2(v0y, v0x);
        a_along = a0x * cos(heading) + a0y * sin(heading);
        if (has_cap && a_along > 0.0)
            top = cap > speed ? cap : speed; /* Python's max(speed, cap) */
    }
    for (n = 0; n < horizon; n++) {
        const double t = (double)n * dt;
        const double wt = w * t;
        double vx, vy, ax, ay, psi_q, c, s, vvx, vvy;
        if (moving) {
            double sp = speed + a_along * t, acc = a_along, hd, ch, sh, spw;
            if (!(sp > 0.0))
                sp = 0.0;
            if (sp >= top) {
                acc = 0.0;
                if (top < sp)
                    sp = top;
            }
            hd = heading + wt;
            ch = cos(hd);
            sh = sin(hd);
            vx = sp * ch;
            vy = sp * sh;
            spw = sp * w;
            ax = acc * ch - spw * sh;
            ay = acc * sh + spw * ch;
        } else {
            vx = v0x + a0x * t;
            vy = v0y + a0y * t;
            ax = a0x;
            ay = a0y;
        }
        psi_q = yaw_q + wt;
        c = cos(psi_q);
        s = sin(psi_q);
        vvx = c * vx + s * vy;
        vvy = -s * vx + c * vy;
        v_v[2 * n] = vvx;
        v_v[2 * n + 1] = vvy;
        vdot[2 * n] = c * ax + s * ay + w * vvy;
        vdot[2 * n + 1] = -s * ax + c * ay + w * -vvx;
        psidot[n] = w;
        if (has_d) {
            d_out[3 * n] = c * d0 + s * d1;
            d_out[3 * n + 1] = -s * d0 + c * d1;
            d_out[3 * n + 2] = d2;
        }
    }
    for (k = 0; k < n_out; k++)
        if (!isfinite(out[k]))
            return 1;
    return 0;
}
