#include "fixed.h"

bool fx_parse(const char *s, int64_t *out)
{
    bool neg = false;
    if (*s == '+' || *s == '-') {
        neg = (*s == '-');
        s++;
    }
    int64_t whole = 0;
    int int_digits = 0, frac_digits = 0;
    int64_t frac = 0;
    bool round_up = false;
    while (*s >= '0' && *s <= '9') {
        if (++int_digits > 12) {
            return false; /* > 10^12 s or V: nothing real, and it keeps int64 safe */
        }
        whole = whole * 10 + (*s++ - '0');
    }
    if (*s == '.') {
        s++;
        while (*s >= '0' && *s <= '9') {
            if (frac_digits < 6) {
                frac = frac * 10 + (*s - '0');
            } else if (frac_digits == 6) {
                round_up = (*s >= '5');
            }
            frac_digits++;
            s++;
        }
    }
    if (*s != '\0' || (int_digits == 0 && frac_digits == 0)) {
        return false;
    }
    for (int d = frac_digits; d < 6; d++) {
        frac *= 10;
    }
    int64_t v = whole * FX_ONE + frac + (round_up ? 1 : 0);
    *out = neg ? -v : v;
    return true;
}

size_t fx_format(char *buf, size_t cap, int64_t micro)
{
    char tmp[32];
    size_t n = 0;
    bool neg = micro < 0;
    uint64_t mag = neg ? (uint64_t)(-(micro + 1)) + 1u : (uint64_t)micro;
    uint64_t whole = mag / FX_ONE, frac = mag % FX_ONE;
    /* fraction: 6 digits, trailing zeros dropped */
    char fd[6];
    for (int i = 5; i >= 0; i--) {
        fd[i] = (char)('0' + frac % 10);
        frac /= 10;
    }
    int flen = 6;
    while (flen > 0 && fd[flen - 1] == '0') {
        flen--;
    }
    /* whole part, reversed into tmp */
    char wd[24];
    int wlen = 0;
    do {
        wd[wlen++] = (char)('0' + whole % 10);
        whole /= 10;
    } while (whole > 0);
    if (neg && !(wlen == 1 && wd[0] == '0' && flen == 0)) {
        tmp[n++] = '-';
    }
    while (wlen > 0) {
        tmp[n++] = wd[--wlen];
    }
    if (flen > 0) {
        tmp[n++] = '.';
        for (int i = 0; i < flen; i++) {
            tmp[n++] = fd[i];
        }
    }
    if (cap == 0) {
        return 0;
    }
    size_t k = n < cap - 1 ? n : cap - 1;
    for (size_t i = 0; i < k; i++) {
        buf[i] = tmp[i];
    }
    buf[k] = '\0';
    return k;
}
