#include "level.h"

#include <math.h>

/* 10^(att/20) for att a multiple of 20 dB, exact; 0 otherwise (the double path is used). */
static int64_t exact_gain(uint8_t att_db)
{
    if (att_db % 20u != 0u) {
        return 0;
    }
    int64_t g = 1;
    for (unsigned k = 0; k < att_db / 20u; k++) {
        g *= 10;
    }
    return g;
}

static double gain_d(uint8_t att_db)
{
    /* integer operands only: the ARM build makes bare floating constants single precision */
    return pow((double)10, (double)att_db / (double)20);
}

int64_t level_code(const converter_t *cv, int64_t amp_uv, uint8_t att_db)
{
    int64_t g = exact_gain(att_db);
    int64_t den = 2 * cv->fsv_uv;
    if (g) {
        /* amp <= 1e9, g <= 1e3, 2^bits <= 65536: the product stays below 2^63 */
        int64_t num = amp_uv * g * ((int64_t)1 << cv->bits);
        return (2 * num + den) / (2 * den);
    }
    double x = (double)amp_uv * gain_d(att_db) * (double)((int64_t)1 << cv->bits) / (double)den;
    return (int64_t)floor(x + (double)1 / (double)2);
}

int64_t level_played_uv(const converter_t *cv, int64_t code, uint8_t att_db)
{
    int64_t g = exact_gain(att_db);
    int64_t num = code * 2 * cv->fsv_uv;
    if (g) {
        int64_t den = ((int64_t)1 << cv->bits) * g;
        return (2 * num + den) / (2 * den);
    }
    double x = (double)num / ((double)((int64_t)1 << cv->bits) * gain_d(att_db));
    return (int64_t)floor(x + (double)1 / (double)2);
}

int64_t level_code_limit(const converter_t *cv, int64_t limit_uv, uint8_t att_db)
{
    int64_t g = exact_gain(att_db);
    int64_t den = 2 * cv->fsv_uv;
    int64_t code;
    if (g) {
        code = limit_uv * g * ((int64_t)1 << cv->bits) / den;
    } else {
        code = (int64_t)floor((double)limit_uv * gain_d(att_db) *
                              (double)((int64_t)1 << cv->bits) / (double)den);
    }
    int64_t top = ((int64_t)1 << (cv->bits - 1)) - 1;
    return code < top ? code : top;
}

int64_t level_default_linear(uint8_t bits)
{
    return ((int64_t)LEVEL_REF_LINEAR_CODES << bits) / (2 * LEVEL_REF_HALF_CODES);
}
